//! Optimisation of the Gaussians' parameters: Adam over the structure-of-arrays groups, kept
//! in step with the map as Gaussians are added, cloned, split and pruned.

// Real -> f64 via f64::from is lossless, and a no-op under the `f64` feature.
#![allow(clippy::useless_conversion)]

mod adam;
mod groups;

pub use adam::{normalize_quats, Adam, AdamConfig, ExpDecay};
pub use groups::Groups;
