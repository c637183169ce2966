//! Pruning: Gaussians that have become transparent, or grown too large in the world or on
//! screen, are removed.

use super::store::GaussianMap;
use crate::raster::math::sigmoid;
use crate::Real;

#[derive(Clone, Copy, Debug)]
pub struct PruneConfig {
    /// Remove below this opacity (the paper's 0.02).
    pub min_opacity: Real,
    /// Remove when the largest standard deviation exceeds this fraction of the scene extent.
    pub max_world_scale: Real,
    /// Remove when the screen-space extent exceeds this many pixels in a training view
    /// (0 disables).
    pub max_screen_radius: Real,
}

impl Default for PruneConfig {
    fn default() -> Self {
        PruneConfig {
            min_opacity: 0.02,
            max_world_scale: 0.1,
            max_screen_radius: 0.0,
        }
    }
}

/// Which Gaussians to keep. `max_radii`: per Gaussian, the largest screen extent seen since
/// the last pruning (pixels), when tracked.
pub fn keep_mask(
    map: &GaussianMap,
    extent: Real,
    max_radii: Option<&[Real]>,
    cfg: &PruneConfig,
) -> Vec<bool> {
    (0..map.len())
        .map(|i| {
            let opaque = sigmoid(map.opacity_logits[i]) >= cfg.min_opacity;
            let s = &map.log_scales[3 * i..3 * i + 3];
            let largest = s[0].max(s[1]).max(s[2]).exp();
            let small = largest <= cfg.max_world_scale * extent;
            let on_screen_ok = cfg.max_screen_radius <= 0.0
                || max_radii.is_none_or(|r| r[i] <= cfg.max_screen_radius);
            opaque && small && on_screen_ok
        })
        .collect()
}
