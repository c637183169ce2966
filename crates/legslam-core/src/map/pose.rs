//! Keyframe pose refinement during mapping: each keyframe's pose is a parameter too, moved by
//! Adam along the rasterizer's pose gradient (a left twist of the world-to-camera pose), so
//! that keyframes the tracker placed slightly apart become photometrically consistent.

use nalgebra::Vector6;

use crate::camera::{se3, Pose};
use crate::optim::SmallAdam;
use crate::Real;

/// Adam state of one keyframe's pose (translation first, as the twist).
pub type PoseAdam = SmallAdam<6>;

/// One Adam step on the camera-to-world `pose` given d(loss)/d(xi) for
/// `T_cw(xi) = exp(xi^) T_cw`, with learning rates (translation in metres, rotation in radians)
/// per step. Returns the new camera-to-world pose.
pub fn step_pose(adam: &mut PoseAdam, pose: &Pose, grad: &[Real; 6], lr: [f64; 2]) -> Pose {
    let g = grad.map(f64::from);
    let delta = adam.step(&g, &[lr[0], lr[0], lr[0], lr[1], lr[1], lr[1]]);
    let moved = se3::exp(&Vector6::from(delta)) * se3::inverse(pose);
    se3::inverse(&se3::orthonormalize(&moved))
}
