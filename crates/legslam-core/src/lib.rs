//! legslam engine: everything numeric and hot, with no Python in it.
//!
//! - [`raster`]: the differentiable Gaussian rasterizer (forward and hand-written backward).
//! - [`camera`]: pinhole intrinsics, the pose type and its SE(3) algebra, depth registration.
//! - [`map`]: the Gaussian map and how it grows, is pruned, densified and trained.
//! - [`track`]: dense RGB-D pose tracking.
//! - [`graph`]: pose-graph optimisation of keyframe poses (loop closure).
//! - [`loss`]: the mapper's image losses (L1, SSIM, depth, feature cosine) with gradients.
//! - [`optim`]: Adam over the Gaussians' parameter groups, following rows as they come and go.
//! - [`options`]: every configuration's options by name, for files and bindings.

pub mod camera;
pub mod graph;
pub mod loss;
pub mod map;
pub mod optim;
pub mod options;
mod prefetch;
pub mod raster;
pub mod rng;
mod rows;
pub mod track;

/// The engine's scalar type: `f32` in every build users run, `f64` under the `f64` feature so
/// that finite-difference tests can check gradients with tiny steps.
#[cfg(not(feature = "f64"))]
pub type Real = f32;
#[cfg(feature = "f64")]
pub type Real = f64;
