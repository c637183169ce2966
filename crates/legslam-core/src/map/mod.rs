//! The Gaussian map and everything that changes it: growth from keyframes, pruning,
//! densification, and training against keyframes (and their poses and exposures).

pub mod correct;
pub mod densify;
pub mod exposure;
pub mod features;
pub mod grow;
pub mod keyframe;
pub mod order;
pub mod pose;
pub mod prune;
pub mod store;
pub mod tally;
pub mod train;

pub use features::FeatureGrid;
pub use keyframe::{Keyframe, Level};
pub use store::{GaussianMap, NewGaussian};
pub use train::{Mapper, MapperConfig, TrainReport};
