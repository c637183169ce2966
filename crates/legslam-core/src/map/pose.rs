//! Keyframe pose refinement during mapping: each keyframe's pose is a parameter too, moved by
//! Adam along the rasterizer's pose gradient (a left twist of the world-to-camera pose), so
//! that keyframes the tracker placed slightly apart become photometrically consistent.

use nalgebra::{Matrix4, Vector6};

use crate::camera::{invert_rigid, Pose};
use crate::track::se3;
use crate::Real;

/// Adam state of one keyframe's pose (translation first, as the twist).
#[derive(Clone, Debug, Default)]
pub struct PoseAdam {
    m: [f64; 6],
    v: [f64; 6],
    steps: u64,
}

impl PoseAdam {
    /// Steps taken so far.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// One Adam step on the camera-to-world `pose` given d(loss)/d(xi) for
    /// `T_cw(xi) = exp(xi^) T_cw`, with learning rates (translation in metres, rotation in
    /// radians) per step. Returns the new camera-to-world pose.
    pub fn step(&mut self, pose: &Pose, grad: &[Real; 6], lr: [f64; 2]) -> Pose {
        const BETA1: f64 = 0.9;
        const BETA2: f64 = 0.999;
        const EPS: f64 = 1e-15;
        self.steps += 1;
        let t = self.steps as f64;
        let (b1, b2) = (1.0 - BETA1.powf(t), 1.0 - BETA2.powf(t));
        let mut delta = Vector6::zeros();
        for a in 0..6 {
            let g = f64::from(grad[a]);
            self.m[a] = BETA1 * self.m[a] + (1.0 - BETA1) * g;
            self.v[a] = BETA2 * self.v[a] + (1.0 - BETA2) * g * g;
            let lr = if a < 3 { lr[0] } else { lr[1] };
            delta[a] = -lr * (self.m[a] / b1) / ((self.v[a] / b2).sqrt() + EPS);
        }
        let w2c = Matrix4::from_fn(|i, j| invert_rigid(pose)[i][j]);
        let moved = se3::orthonormalize(&(se3::exp(&delta) * w2c));
        let c2w = se3::inverse(&moved);
        std::array::from_fn(|i| std::array::from_fn(|j| c2w[(i, j)]))
    }
}
