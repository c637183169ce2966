//! Dense RGB-D camera tracking.
//!
//! Aligns a new RGB-D [`Frame`] to a [`Reference`] view of known pose (a previous keyframe,
//! or colour + depth rendered from the Gaussian map at the predicted pose) by Gauss-Newton
//! over SE(3) on a joint robust cost:
//!
//! - geometric point-to-plane residuals with projective data association,
//! - photometric intensity residuals with the reference's image gradients,
//!
//! each Huber-weighted, coarse-to-fine over an image pyramid, with the 6x6 normal equations
//! reduced in parallel (rayon, deterministic for any thread count) and solved with nalgebra.
//! See [`solve`] for the residuals and [`crate::camera::se3`] for the twist convention (`xi = (v, w)`,
//! translation first, left perturbation `T <- exp(delta) T`).
//!
//! Poses at the API are `f64` 4x4 camera-to-world (`T_wc`), OpenCV camera axes.
//!
//! Every [`TrackResult`] carries quality signals (residual, inlier ratio, condition of the
//! normal equations) and a `lost` verdict, so that the SLAM loop can refuse to map from a
//! pose that cannot be trusted.
//!
//! [`Odometry`] chains frame-to-frame tracking with a constant-velocity motion prior.
//! [`Tsdf`] fuses tracked frames' depth into the surface a frame is tracked against.

mod image;
#[cfg(target_arch = "x86_64")]
mod lanes;
mod solve;
mod tsdf;

pub use image::{Color, Frame, Reference};
pub use tsdf::{Tsdf, TsdfConfig};

use nalgebra::{Matrix6, SymmetricEigen, Vector6};

use crate::camera::{se3, Pose};

use solve::{accumulate, Params, RefLevel, Sums};

/// Tracker settings. `Default` gives the values tuned on 7-Scenes (640x480 Kinect).
#[derive(Clone, Debug, PartialEq)]
pub struct TrackerConfig {
    /// Number of pyramid levels used, from `finest_level` up (coarser) .
    pub levels: usize,
    /// Finest pyramid level used (0 = full resolution, 1 = half, ...). The pyramid is built
    /// from full resolution either way.
    pub finest_level: usize,
    /// Maximum Gauss-Newton iterations per used level, finest first; the last value repeats
    /// if the list is shorter than `levels`.
    pub iterations: Vec<usize>,
    /// Valid depth range (m); depth outside it is treated as invalid.
    pub min_depth: f64,
    pub max_depth: f64,
    /// Largest depth difference (m) between a warped point and the reference depth at its
    /// pixel for the pair to be associated (occlusion / outlier gate).
    pub max_depth_diff: f64,
    /// Huber thresholds: geometric (m) and photometric (intensity in [0, 1]). Residuals are
    /// normalised by them before weighting.
    pub geometric_huber: f64,
    pub photometric_huber: f64,
    /// Weight of the (normalised) photometric term relative to the geometric one; 0 turns it
    /// off (pure point-to-plane ICP).
    pub photometric_weight: f64,
    /// Estimate a global exposure gain between frame and reference (from the mean
    /// intensities of the photometric correspondences, updated every iteration), so that
    /// auto-exposure changes do not bias the photometric term.
    pub estimate_gain: bool,
    /// Photometric residuals are used only where the reference gradient magnitude (intensity
    /// per pixel) is at least this.
    pub min_gradient: f64,
    /// A level stops when the update is smaller than this (|dt| in m + |dw| in rad).
    pub convergence_eps: f64,
    /// Geometric residual (m) below which a correspondence counts as an inlier.
    pub inlier_threshold: f64,
    /// Lost if inliers / valid frame pixels (at the finest level) is below this.
    pub min_inlier_ratio: f64,
    /// Lost if there are fewer inliers than this at the finest level.
    pub min_inliers: usize,
    /// Lost if the condition number of the normal equations (rotation scaled by the mean
    /// scene depth, so that both blocks are in metres) exceeds this.
    pub max_condition: f64,
    /// Lost if the estimate moved further than this from the initial guess (m, degrees).
    pub max_translation: f64,
    pub max_rotation_deg: f64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            // Quarter resolution as the finest level: on 7-Scenes (1000 frames) as accurate
            // as half or full resolution (Kinect depth quantisation and the colour/depth
            // misregistration dominate) at a fraction of the cost; see bench_tracking.py.
            levels: 3,
            finest_level: 2,
            iterations: vec![4, 8, 10],
            min_depth: 0.1,
            max_depth: 6.0,
            max_depth_diff: 0.03,
            geometric_huber: 0.01,
            photometric_huber: 0.05,
            photometric_weight: 3.0,
            estimate_gain: true,
            min_gradient: 0.0,
            convergence_eps: 1e-5,
            inlier_threshold: 0.02,
            min_inlier_ratio: 0.35,
            min_inliers: 300,
            max_condition: 1e4,
            max_translation: 0.3,
            max_rotation_deg: 20.0,
        }
    }
}

impl TrackerConfig {
    /// Checks every field; the message names the offending one.
    pub fn validate(&self) -> Result<(), String> {
        crate::options::check_finite("tracker", self)?;
        if self.levels == 0 || self.levels > 8 {
            return Err(format!("levels must be 1..=8, got {}", self.levels));
        }
        if self.finest_level > 4 {
            return Err(format!(
                "finest_level must be 0..=4, got {}",
                self.finest_level
            ));
        }
        if self.iterations.is_empty() {
            return Err("iterations must not be empty".into());
        }
        let pos = [
            ("max_depth", self.max_depth),
            ("max_depth_diff", self.max_depth_diff),
            ("geometric_huber", self.geometric_huber),
            ("photometric_huber", self.photometric_huber),
            ("inlier_threshold", self.inlier_threshold),
            ("max_condition", self.max_condition),
            ("max_translation", self.max_translation),
            ("max_rotation_deg", self.max_rotation_deg),
        ];
        for (name, v) in pos {
            if v.is_nan() || v <= 0.0 {
                return Err(format!("{name} must be positive, got {v}"));
            }
        }
        let nonneg = [
            ("min_depth", self.min_depth),
            ("photometric_weight", self.photometric_weight),
            ("min_gradient", self.min_gradient),
            ("convergence_eps", self.convergence_eps),
            ("min_inlier_ratio", self.min_inlier_ratio),
        ];
        for (name, v) in nonneg {
            if !v.is_finite() || v < 0.0 {
                return Err(format!("{name} must be finite and >= 0, got {v}"));
            }
        }
        if self.min_depth >= self.max_depth {
            return Err(format!(
                "min_depth ({}) must be below max_depth ({})",
                self.min_depth, self.max_depth
            ));
        }
        Ok(())
    }

    fn iterations_at(&self, i: usize) -> usize {
        *self
            .iterations
            .get(i)
            .unwrap_or_else(|| self.iterations.last().unwrap_or(&0))
    }
}

// Every option of [`TrackerConfig`] by name (see [`crate::options`]).
crate::options!(TrackerConfig, "tracker", {
    "levels" => levels,
    "finest_level" => finest_level,
    "iterations" => iterations,
    "min_depth" => min_depth,
    "max_depth" => max_depth,
    "max_depth_diff" => max_depth_diff,
    "geometric_huber" => geometric_huber,
    "photometric_huber" => photometric_huber,
    "photometric_weight" => photometric_weight,
    "estimate_gain" => estimate_gain,
    "min_gradient" => min_gradient,
    "convergence_eps" => convergence_eps,
    "inlier_threshold" => inlier_threshold,
    "min_inlier_ratio" => min_inlier_ratio,
    "min_inliers" => min_inliers,
    "max_condition" => max_condition,
    "max_translation" => max_translation,
    "max_rotation_deg" => max_rotation_deg,
});

/// The outcome of one alignment.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackResult {
    /// Estimated camera-to-world pose of the frame. When `lost`, the best estimate found
    /// (or the initial guess if no estimate could be made) that should not be trusted.
    pub pose: Pose,
    /// RMS of the Huber-normalised joint residual (dimensionless), at the last iteration.
    pub residual_rms: f64,
    /// RMS point-to-plane distance of the inliers (m).
    pub geometric_rms: f64,
    /// RMS intensity residual of the photometric terms (intensity in [0, 1]).
    pub photometric_rms: f64,
    /// Inlier correspondences / frame pixels with valid depth, at the finest level.
    pub inlier_ratio: f64,
    /// Number of inlier correspondences at the finest level.
    pub inliers: usize,
    /// Condition number of the (depth-scaled) normal equations at the finest level;
    /// infinite if singular.
    pub condition: f64,
    /// Gauss-Newton iterations over all levels.
    pub iterations: usize,
    /// Estimated exposure gain (frame intensity is multiplied by it), 1 if not estimated.
    pub gain: f64,
    /// The alignment cannot be trusted.
    pub lost: bool,
    /// Why it is lost (`None` when not lost).
    pub reason: Option<String>,
}

/// Aligns `frame` to `reference`, starting from the guess `init` (camera-to-world of the
/// frame). Errors only on inconsistent inputs (different pyramid or intrinsics, bad pose);
/// an alignment that fails numerically is reported as `lost`.
pub fn track(
    reference: &Reference,
    frame: &Frame,
    init: &Pose,
    config: &TrackerConfig,
) -> Result<TrackResult, String> {
    config.validate()?;
    se3::validate_pose(init, "initial pose")?;
    let nl = config.finest_level + config.levels;
    if frame.num_levels() != nl || reference.frame.num_levels() != nl {
        return Err(format!(
            "frame ({} levels) and reference ({} levels) must be prepared with the \
             config's {} pyramid levels",
            frame.num_levels(),
            reference.frame.num_levels(),
            nl
        ));
    }
    let (kf, kr) = (&frame.intrinsics, &reference.frame.intrinsics);
    if kf.width != kr.width || kf.height != kr.height {
        return Err(format!(
            "frame is {}x{} but the reference is {}x{}",
            kf.width, kf.height, kr.width, kr.height
        ));
    }
    let mut params = Params::new(config);
    let t_rw = se3::inverse(&reference.pose);
    // Relative pose of the frame in the reference camera; the unknown.
    let init = &se3::orthonormalize(init);
    let mut t_rf = t_rw * init;
    let mut iterations = 0;
    let mut last = Sums::default();
    let mut last_h = Matrix6::zeros();
    let mut failure: Option<String> = None;
    if frame.valid_pixels == 0 {
        failure = Some("the frame has no valid depth".into());
    } else if reference.frame.valid_pixels == 0 {
        failure = Some("the reference has no valid depth".into());
    }
    'levels: for (i, l) in (config.finest_level..nl).enumerate().rev() {
        if failure.is_some() {
            break;
        }
        let rl = RefLevel {
            lev: &reference.frame.levels[l],
            igd: &reference.igd[l],
            normals: &reference.normals[l],
        };
        let fl = &frame.levels[l];
        for _ in 0..config.iterations_at(i) {
            let (rot, t) = to_f32(&t_rf);
            let s = accumulate(&rl, fl, &rot, &t, &params);
            iterations += 1;
            if config.estimate_gain && s.n_photo >= 100 && s.sum_if > 0.0 {
                params.gain = (s.sum_ir / s.sum_if).clamp(0.5, 2.0) as f32;
            }
            let h = sym6(&s.h);
            let b = Vector6::from_row_slice(&s.b);
            last_h = h;
            let n_terms = s.n_geo + s.n_photo;
            last = s;
            if n_terms < 6 {
                if l == config.finest_level {
                    failure = Some("no correspondences between frame and reference".into());
                    break 'levels;
                }
                // A coarse level may have too little overlap; try the next finer one.
                break;
            }
            let scale = h.diagonal().max().max(1e-12);
            let damped = h + Matrix6::identity() * (1e-9 * scale);
            let Some(chol) = damped.cholesky() else {
                failure = Some("singular normal equations".into());
                break 'levels;
            };
            let delta = -chol.solve(&b);
            if delta.iter().any(|v| !v.is_finite()) {
                failure = Some("non-finite update".into());
                break 'levels;
            }
            t_rf = se3::exp(&delta) * t_rf;
            let step = delta.fixed_rows::<3>(0).norm() + delta.fixed_rows::<3>(3).norm();
            if step < config.convergence_eps {
                break;
            }
        }
    }
    let mut pose = reference.pose * t_rf;
    if pose.iter().any(|v| !v.is_finite()) {
        pose = *init;
        failure.get_or_insert_with(|| "non-finite pose".into());
    }
    // Quality signals from the last pass (at the finest level unless it failed earlier).
    let n_terms = (last.n_geo + last.n_photo).max(1) as f64;
    let residual_rms = (2.0 * last.cost / n_terms).sqrt();
    let geometric_rms = (last.sq_geo / (last.n_inlier.max(1) as f64)).sqrt();
    let photometric_rms = (last.sq_photo / (last.n_photo.max(1) as f64)).sqrt();
    let inlier_ratio = if last.n_valid > 0 {
        last.n_inlier as f64 / last.n_valid as f64
    } else {
        0.0
    };
    let condition = condition_number(&last_h, &last);
    let mut reason = failure;
    if reason.is_none() {
        let rel = se3::inverse(init) * pose;
        let dt = se3::translation(&rel).norm();
        let dr = se3::rotation_angle(&rel).to_degrees();
        reason = if (last.n_inlier as usize) < config.min_inliers {
            Some(format!(
                "too few inliers ({} < {})",
                last.n_inlier, config.min_inliers
            ))
        } else if inlier_ratio < config.min_inlier_ratio {
            Some(format!(
                "inlier ratio {inlier_ratio:.3} < {}",
                config.min_inlier_ratio
            ))
        } else if condition.is_nan() || condition > config.max_condition {
            Some(format!(
                "ill-conditioned normal equations (condition {condition:.3e} > {:.1e})",
                config.max_condition
            ))
        } else if dt > config.max_translation || dr > config.max_rotation_deg {
            Some(format!(
                "implausible motion from the initial guess ({dt:.3} m, {dr:.1} deg)"
            ))
        } else {
            None
        };
    }
    Ok(TrackResult {
        pose,
        residual_rms: finite_or(residual_rms, 0.0),
        geometric_rms: finite_or(geometric_rms, 0.0),
        photometric_rms: finite_or(photometric_rms, 0.0),
        inlier_ratio,
        inliers: last.n_inlier as usize,
        condition,
        iterations,
        gain: params.gain as f64,
        lost: reason.is_some(),
        reason,
    })
}

fn finite_or(v: f64, d: f64) -> f64 {
    if v.is_finite() {
        v
    } else {
        d
    }
}

fn to_f32(t: &Pose) -> ([[f32; 3]; 3], [f32; 3]) {
    let mut r = [[0.0f32; 3]; 3];
    for (i, row) in r.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = t[(i, j)] as f32;
        }
    }
    (r, [t[(0, 3)] as f32, t[(1, 3)] as f32, t[(2, 3)] as f32])
}

fn sym6(h: &[f64; 21]) -> Matrix6<f64> {
    let mut m = Matrix6::zeros();
    let mut k = 0;
    for i in 0..6 {
        for j in i..6 {
            m[(i, j)] = h[k];
            m[(j, i)] = h[k];
            k += 1;
        }
    }
    m
}

/// Condition number of `H` with the rotation block scaled by the mean correspondence depth
/// (so that a rotation and a translation that move points equally weigh the same).
fn condition_number(h: &Matrix6<f64>, s: &Sums) -> f64 {
    if s.n_geo == 0 && s.n_photo == 0 {
        return f64::INFINITY;
    }
    let d = if s.n_geo > 0 {
        (s.depth_sum / s.n_geo as f64).max(0.1)
    } else {
        1.0
    };
    let mut sc = *h;
    for i in 0..6 {
        for j in 0..6 {
            let a = if i >= 3 { 1.0 / d } else { 1.0 };
            let b = if j >= 3 { 1.0 / d } else { 1.0 };
            sc[(i, j)] *= a * b;
        }
    }
    if sc.iter().any(|v| !v.is_finite()) {
        return f64::INFINITY;
    }
    let eig = SymmetricEigen::new(sc).eigenvalues;
    let (mn, mx) = (eig.min(), eig.max());
    if mn <= 0.0 || !mn.is_finite() {
        f64::INFINITY
    } else {
        mx / mn
    }
}

/// One step of [`Odometry`].
#[derive(Clone, Debug)]
pub struct OdometryStep {
    /// Pose assigned to the frame (camera-to-world): the tracked pose, or the
    /// constant-velocity prediction when tracking was lost.
    pub pose: Pose,
    /// The constant-velocity prediction used as the initial guess.
    pub predicted: Pose,
    /// The alignment (`None` for the first frame).
    pub result: Option<TrackResult>,
}

/// Frame-to-frame RGB-D odometry: each frame is tracked against the previous one, starting
/// from a constant-velocity prediction; a lost frame keeps the prediction (and still becomes
/// the next reference, at that pose).
#[derive(Clone, Debug)]
pub struct Odometry {
    config: TrackerConfig,
    motion_prior: bool,
    reference: Option<Reference>,
    pose: Pose,
    velocity: Pose,
    frames: usize,
    lost: usize,
}

impl Odometry {
    /// `initial_pose` is given to the first frame; `motion_prior` turns the
    /// constant-velocity prediction on (otherwise the previous pose is the guess).
    pub fn new(
        config: TrackerConfig,
        initial_pose: &Pose,
        motion_prior: bool,
    ) -> Result<Odometry, String> {
        config.validate()?;
        se3::validate_pose(initial_pose, "initial pose")?;
        Ok(Odometry {
            config,
            motion_prior,
            reference: None,
            pose: se3::orthonormalize(initial_pose),
            velocity: Pose::identity(),
            frames: 0,
            lost: 0,
        })
    }

    /// Tracks the next frame.
    pub fn step(&mut self, frame: Frame) -> Result<OdometryStep, String> {
        let predicted = if self.motion_prior {
            self.pose * self.velocity
        } else {
            self.pose
        };
        let (pose, result) = match &self.reference {
            None => (self.pose, None),
            Some(r) => {
                let res = track(r, &frame, &predicted, &self.config)?;
                let p = if res.lost {
                    self.lost += 1;
                    predicted
                } else {
                    res.pose
                };
                (p, Some(res))
            }
        };
        if result.is_some() {
            self.velocity = se3::inverse(&self.pose) * pose;
        }
        self.pose = pose;
        self.reference = Some(Reference::from_frame(frame, &pose, &self.config)?);
        self.frames += 1;
        Ok(OdometryStep {
            pose,
            predicted,
            result,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &TrackerConfig {
        &self.config
    }

    /// Frames processed and frames lost so far.
    pub fn frames(&self) -> usize {
        self.frames
    }
    pub fn lost_frames(&self) -> usize {
        self.lost
    }

    /// Pose of the last frame.
    pub fn pose(&self) -> &Pose {
        &self.pose
    }
}

#[cfg(test)]
mod tests;
