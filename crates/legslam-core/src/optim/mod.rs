//! Optimisation of the Gaussians' parameters: Adam over the structure-of-arrays groups, kept
//! in step with the map as Gaussians are added, cloned, split and pruned; and a small Adam for
//! per-keyframe parameters.

// Real -> f64 via f64::from is lossless, and a no-op under the `f64` feature.
#![allow(clippy::useless_conversion)]

mod adam;
mod groups;
mod small_adam;

pub(crate) use adam::rows_in;
pub use adam::{normalize_quats, Adam, AdamConfig, ExpDecay};
pub use groups::{Groups, LR_NAMES};
pub use small_adam::SmallAdam;
