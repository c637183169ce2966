//! Densification by gradient (3DGS): Gaussians whose projected centres keep receiving large
//! gradients are under-reconstructing; small ones are cloned, large ones split in two.

use super::store::GaussianMap;
use super::tally::Tally;
use crate::raster::math::{quat_to_mat, V3};
use crate::rng::Rng;
use crate::Real;

#[derive(Clone, Copy, Debug)]
pub struct DensifyConfig {
    /// Densify every this many mapping iterations (0 disables).
    pub interval: usize,
    /// Mean norm of d(loss)/d(projected centre) above which a Gaussian densifies, with the
    /// centre in normalised device coordinates (pixels / (size / 2)), as 3DGS and gsplat
    /// measure it, so that their threshold carries over whatever the training resolution.
    pub grad_threshold: Real,
    /// Gaussians larger than this fraction of the scene extent are split, smaller cloned.
    pub split_scale: Real,
    /// Never grow the map (by densification or from keyframes) beyond this many Gaussians.
    pub max_gaussians: usize,
}

impl Default for DensifyConfig {
    fn default() -> Self {
        DensifyConfig {
            interval: 100,
            // 3DGS's 2e-4 clones most of a freshly grown SLAM map (100k of 200k Gaussians in
            // a 7-Scenes run); 1e-3 clones a few percent, where the map needs it.
            grad_threshold: 1e-3,
            split_scale: 0.01,
            max_gaussians: 200_000,
        }
    }
}

/// Adds one iteration's d(loss)/d(means2d) (pixels) of a `width` x `height` render for the
/// Gaussians that were on screen (`visible`) to their gradient norms, converted to normalised
/// device coordinates.
pub fn add_screen_grads(
    stats: &mut Tally,
    means2d: &[Real],
    visible: &[u32],
    width: usize,
    height: usize,
) {
    stats.resize(means2d.len() / 2);
    let (sx, sy) = (0.5 * width as Real, 0.5 * height as Real);
    for &i in visible {
        let i = i as usize;
        let (gx, gy) = (means2d[2 * i] * sx, means2d[2 * i + 1] * sy);
        stats.add(i, (gx * gx + gy * gy).sqrt());
    }
}

/// What one densification did: the rows appended (copies of `sources`) and which old rows to
/// drop afterwards (the split originals).
pub struct Densified {
    pub sources: Vec<usize>,
    pub keep: Vec<bool>,
    pub cloned: usize,
    pub split: usize,
}

/// Clones and splits in place (appending rows) and returns what was done, so that optimiser
/// state can follow: the appended rows are copies of `sources`; then `keep` applies. `stats`:
/// the gradient norms since the last densification (`add_screen_grads`).
pub fn densify(
    map: &mut GaussianMap,
    stats: &Tally,
    extent: Real,
    cfg: &DensifyConfig,
    rng: &mut Rng,
) -> Densified {
    let n = map.len();
    let mut keep = vec![true; n];
    let mut clone_rows = Vec::new();
    let mut split_rows = Vec::new();
    let budget = cfg.max_gaussians.saturating_sub(n);
    for i in 0..n {
        if stats.mean(i).is_none_or(|g| g < cfg.grad_threshold) {
            continue;
        }
        let s = &map.log_scales[3 * i..3 * i + 3];
        if s[0].max(s[1]).max(s[2]).exp() > cfg.split_scale * extent {
            split_rows.push(i);
        } else {
            clone_rows.push(i);
        }
    }
    // Within the budget: a clone adds one row, a split adds two and removes one.
    clone_rows.truncate(budget);
    split_rows.truncate(budget.saturating_sub(clone_rows.len()));
    let mut sources = clone_rows.clone();
    for &i in &split_rows {
        sources.push(i);
        sources.push(i);
        keep[i] = false;
    }
    map.duplicate(&sources);
    // Split children: centres sampled from the parent's distribution, scales / 1.6.
    let first_split = n + clone_rows.len();
    for (j, &src) in sources[clone_rows.len()..].iter().enumerate() {
        let row = first_split + j;
        let q = &map.quats[4 * src..4 * src + 4];
        let r = quat_to_mat(q[0], q[1], q[2], q[3]);
        let s = &map.log_scales[3 * src..3 * src + 3];
        let local = V3::new(
            rng.normal() as Real * s[0].exp(),
            rng.normal() as Real * s[1].exp(),
            rng.normal() as Real * s[2].exp(),
        );
        let offset = r * local;
        for a in 0..3 {
            map.means[3 * row + a] += offset[a];
            map.log_scales[3 * row + a] -= (1.6 as Real).ln();
        }
    }
    keep.resize(map.len(), true);
    Densified {
        sources,
        keep,
        cloned: clone_rows.len(),
        split: split_rows.len(),
    }
}
