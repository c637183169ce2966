//! Differentiable Gaussian rasterizer: EWA projection, tile binning, front-to-back alpha
//! compositing of colour, depth, alpha and K-channel features, and the hand-written backward
//! pass to every Gaussian parameter and to the camera pose.
//!
//! Conventions: pixel centres sit at integer coordinates (OpenCV intrinsics); images are
//! row-major, channel-last; the camera is given world-to-camera. Depth and features are
//! alpha-blended like colour and not divided by the accumulated alpha.
//!
//! Pose gradients are with respect to a twist `xi = (rho, phi)` (translation first) that
//! perturbs the world-to-camera pose on the left: `T_cw(xi) = exp(xi^) * T_cw`.

mod backward;
mod composite;
mod config;
mod forward;
mod lanes;
pub(crate) mod math;
mod project;
mod project_backward;
pub mod sh;
mod tiles;

pub use backward::{backward, backward_into, BackwardScratch};
pub use config::{RasterConfig, TILE};
pub use forward::{render, render_into};
pub use lanes::{
    avx2_available, avx512_available, native_simd, neon_available, vector_paths, Simd,
};

use crate::camera::{Intrinsics, Pose};
use crate::Real;
use math::{mat3_rows, M3, V3};

/// A borrowed structure-of-arrays view of N Gaussians.
#[derive(Clone, Copy, Debug)]
pub struct Gaussians<'a> {
    /// [N, 3] world-space centres.
    pub means: &'a [Real],
    /// [N, 3] natural logarithms of the standard deviations along the local axes.
    pub log_scales: &'a [Real],
    /// [N, 4] unit quaternions (w, x, y, z), local-to-world rotation.
    pub quats: &'a [Real],
    /// [N] opacity logits (opacity = sigmoid(logit)).
    pub opacity_logits: &'a [Real],
    /// [N, sh_coeffs, 3] spherical-harmonic colour coefficients.
    pub sh: &'a [Real],
    /// Coefficients per channel stored in `sh`: 1, 4, 9 or 16.
    pub sh_coeffs: usize,
    /// [N, num_features] language features.
    pub features: &'a [Real],
    /// Feature channels K (0 for none).
    pub num_features: usize,
}

impl Gaussians<'_> {
    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Checks sizes, finiteness and unit quaternions; says which array is wrong and why.
    pub fn validate(&self) -> Result<(), String> {
        let n = self.len();
        if ![1, 4, 9, 16].contains(&self.sh_coeffs) {
            return Err(format!(
                "sh must hold 1, 4, 9 or 16 coefficients per channel (degree 0-3), got {}",
                self.sh_coeffs
            ));
        }
        let groups: [(&str, &[Real], usize); 6] = [
            ("means", self.means, 3),
            ("log_scales", self.log_scales, 3),
            ("quats", self.quats, 4),
            ("opacity_logits", self.opacity_logits, 1),
            ("sh", self.sh, self.sh_coeffs * 3),
            ("features", self.features, self.num_features),
        ];
        for (name, data, width) in groups {
            if data.len() != n * width {
                return Err(format!(
                    "{name} must hold {n} x {width} values for {n} Gaussians, got {}",
                    data.len()
                ));
            }
            if let Some(i) = data.iter().position(|v| !v.is_finite()) {
                return Err(format!(
                    "{name} has a non-finite value (NaN or inf) at Gaussian {}",
                    i / width.max(1)
                ));
            }
        }
        for (i, q) in self.quats.chunks_exact(4).enumerate() {
            let norm = q.iter().map(|v| v * v).sum::<Real>().sqrt();
            if (norm - 1.0).abs() > 1e-3 {
                return Err(format!(
                    "quats must be unit quaternions (w, x, y, z); Gaussian {i} has norm {norm}"
                ));
            }
        }
        Ok(())
    }
}

/// A pinhole camera: intrinsics and the world-to-camera pose.
#[derive(Clone, Copy, Debug)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    /// Rotation of the world-to-camera pose.
    pub rotation: M3,
    /// Translation of the world-to-camera pose.
    pub translation: V3,
}

impl Camera {
    /// A camera from intrinsics and its world-to-camera pose.
    pub fn new(intrinsics: Intrinsics, world_to_camera: &Pose) -> Result<Self, String> {
        intrinsics.validate()?;
        let m = world_to_camera;
        if m.iter().any(|v| !v.is_finite()) {
            return Err("the camera pose has a non-finite entry".into());
        }
        let last = [m[(3, 0)], m[(3, 1)], m[(3, 2)], m[(3, 3)]];
        if last != [0.0, 0.0, 0.0, 1.0] {
            return Err(format!(
                "the camera pose's last row must be [0, 0, 0, 1], got {last:?}"
            ));
        }
        let row = |i: usize| V3::new(m[(i, 0)] as Real, m[(i, 1)] as Real, m[(i, 2)] as Real);
        let rotation = mat3_rows(row(0), row(1), row(2));
        let off = (rotation * rotation.transpose() - M3::IDENTITY)
            .to_cols_array()
            .iter()
            .fold(0.0 as Real, |a, v| a.max(v.abs()));
        if off > 1e-3 || rotation.determinant() < 0.0 {
            return Err(format!(
                "the camera pose's rotation is not a rotation (|R R^T - I| = {off})"
            ));
        }
        let translation = V3::new(m[(0, 3)] as Real, m[(1, 3)] as Real, m[(2, 3)] as Real);
        Ok(Camera {
            intrinsics,
            rotation,
            translation,
        })
    }

    /// Camera centre in world coordinates.
    pub fn position(&self) -> V3 {
        -(self.rotation.transpose() * self.translation)
    }
}

/// What to render and how.
#[derive(Clone, Copy, Debug)]
pub struct RenderOptions {
    /// SH degree used for colour (at most the degree the stored coefficients allow).
    pub sh_degree: usize,
    pub color: bool,
    pub depth: bool,
    pub alpha: bool,
    pub features: bool,
    /// Features are rendered this many times coarser than the other images (width / s by
    /// height / s, intrinsics scaled about pixel centres) from the same projection: a feature
    /// target holds little detail, and K channels cost K times a colour channel.
    pub feature_scale: usize,
    /// Where the coarse features' pixels sample the image: `None`, each pixel is the coarse
    /// render of its `feature_scale`-square block (its footprints dilated again at the coarse
    /// scale); `Some(o)`, pixel (i, j) is the main layer's image at the point
    /// (s i + o[0], s j + o[1]) (the main layer's footprints, point-sampled).
    pub feature_origin: Option<[Real; 2]>,
    pub config: RasterConfig,
    /// Which compositing implementation runs (the results are the same bits either way).
    pub simd: Simd,
    /// Keep what the backward pass would evaluate again: each walked group of eight pixels'
    /// exponential (32 bytes a group; about 27 MB for a 320x240 render of the mapper bench's map
    /// with features at 160x120). A training loop's render asks for it, and its backward pass
    /// then skips the exponential (the same bits either way).
    pub for_backward: bool,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            sh_degree: 0,
            color: true,
            depth: true,
            alpha: true,
            features: true,
            feature_scale: 1,
            feature_origin: None,
            config: RasterConfig::default(),
            simd: Simd::Auto,
            for_backward: false,
        }
    }
}

/// Rendered images (empty when not requested) and the state the backward pass needs.
#[derive(Clone, Debug, Default)]
pub struct Rendered {
    pub width: usize,
    pub height: usize,
    pub num_features: usize,
    /// The size of the feature image (the other images' at `feature_scale` 1).
    pub feature_width: usize,
    pub feature_height: usize,
    /// [H, W, 3]
    pub color: Vec<Real>,
    /// [H, W] alpha-blended camera-space z.
    pub depth: Vec<Real>,
    /// [H, W] accumulated opacity, 1 - final transmittance.
    pub alpha: Vec<Real>,
    /// [feature_height, feature_width, K]
    pub features: Vec<Real>,
    /// Per Gaussian: screen-space half extent in pixels (0 when not in the main layer).
    pub radii: Vec<Real>,
    pub(crate) state: forward::State,
}

impl Rendered {
    /// Number of (tile, Gaussian) pairs composited: the work the rasterizer did.
    pub fn num_pairs(&self) -> usize {
        self.state.main.bins.pair_gauss.len() + self.state.coarse.bins.pair_gauss.len()
    }
}

/// d(loss)/d(each rendered image), laid out like the images; `None` for an image that does
/// not enter the loss.
#[derive(Clone, Copy, Debug, Default)]
pub struct ImageGrads<'a> {
    pub color: Option<&'a [Real]>,
    pub depth: Option<&'a [Real]>,
    pub alpha: Option<&'a [Real]>,
    pub features: Option<&'a [Real]>,
}

/// d(loss)/d(every input), laid out like the inputs.
#[derive(Clone, Debug, Default)]
pub struct Gradients {
    pub means: Vec<Real>,
    pub log_scales: Vec<Real>,
    pub quats: Vec<Real>,
    pub opacity_logits: Vec<Real>,
    pub sh: Vec<Real>,
    pub features: Vec<Real>,
    /// [N, 2] gradient with respect to the projected centres in pixels (for densification).
    pub means2d: Vec<Real>,
    /// With respect to the left twist (rho, phi) of the world-to-camera pose.
    pub pose: [Real; 6],
    /// [N] not a gradient: each Gaussian's blending weights alpha * T summed over the main
    /// layer's pixels, how much of the image it makes (pruning removes what makes nothing).
    pub contribution: Vec<Real>,
    /// The Gaussians on screen, in order: the rows the pass wrote. The others are zero in a
    /// fresh `Gradients`; [`backward_into`] leaves them as the last pass did (stale), for
    /// callers that read only these rows, as `Adam::step_rows` does.
    pub rows: Vec<u32>,
}

impl Gradients {
    /// Every per-Gaussian array: the parameter groups, then `means2d` and `contribution`.
    pub fn arrays_mut(&mut self) -> [&mut Vec<Real>; 8] {
        [
            &mut self.means,
            &mut self.log_scales,
            &mut self.quats,
            &mut self.opacity_logits,
            &mut self.sh,
            &mut self.features,
            &mut self.means2d,
            &mut self.contribution,
        ]
    }
}
