//! Binning of projected Gaussians into screen tiles, each tile's list sorted front to back.

use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};

use rayon::prelude::*;

use super::forward::Splat;
use super::math::{floor_end_in, floor_in};
use super::TILE;
use crate::Real;

/// Tile grid of an image.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Grid {
    pub tiles_x: usize,
    pub tiles_y: usize,
}

impl Grid {
    pub fn new(width: usize, height: usize) -> Self {
        Grid {
            tiles_x: width.div_ceil(TILE),
            tiles_y: height.div_ceil(TILE),
        }
    }

    pub fn len(&self) -> usize {
        self.tiles_x * self.tiles_y
    }
}

/// Tile rectangle [x0, x1) x [y0, y1) in tile units; empty when culled.
pub(crate) type Rect = [u32; 4];

/// The tiles whose pixels a Gaussian at `xy` with half extents `ext` may touch.
#[inline]
pub(crate) fn rect(grid: &Grid, x: Real, y: Real, ex: Real, ey: Real) -> Rect {
    let t = TILE as Real;
    let lo = |v: Real, n: usize| floor_in(v / t, n) as u32;
    let hi = |v: Real, n: usize| floor_end_in(v / t, n) as u32;
    [
        lo(x - ex, grid.tiles_x),
        lo(y - ey, grid.tiles_y),
        hi(x + ex, grid.tiles_x),
        hi(y + ey, grid.tiles_y),
    ]
}

#[inline]
pub(crate) fn rect_area(r: &Rect) -> usize {
    (r[2].saturating_sub(r[0]) as usize) * (r[3].saturating_sub(r[1]) as usize)
}

/// Calls `f` with the index of every tile in `r`.
#[inline]
fn for_each_tile(grid: &Grid, r: &Rect, mut f: impl FnMut(usize)) {
    for ty in r[1]..r[3] {
        let row = ty as usize * grid.tiles_x;
        for tx in r[0]..r[2] {
            f(row + tx as usize);
        }
    }
}

/// Per-tile lists: tile `t` composites `pair_gauss[tile_start[t]..tile_start[t + 1]]`.
#[derive(Clone, Debug, Default)]
pub(crate) struct Bins {
    pub tile_start: Vec<u32>,
    pub pair_gauss: Vec<u32>,
}

impl Bins {
    /// Tile `t`'s Gaussians, front to back.
    #[inline]
    pub fn list(&self, t: usize) -> &[u32] {
        &self.pair_gauss[self.tile_start[t] as usize..self.tile_start[t + 1] as usize]
    }
}

/// Bins Gaussians by tile and sorts each tile by depth, ties by index. The keys are unique,
/// so the result does not depend on the order the parallel fill happens to run in.
pub(crate) fn bin(grid: &Grid, rects: &[Rect], splats: &[Splat]) -> Bins {
    let n_tiles = grid.len();
    let counts: Vec<AtomicU32> = (0..n_tiles).map(|_| AtomicU32::new(0)).collect();
    rects.par_iter().with_min_len(4096).for_each(|r| {
        for_each_tile(grid, r, |t| {
            counts[t].fetch_add(1, Ordering::Relaxed);
        })
    });
    let mut tile_start = vec![0u32; n_tiles + 1];
    for t in 0..n_tiles {
        tile_start[t + 1] = tile_start[t] + counts[t].load(Ordering::Relaxed);
    }
    let total = tile_start[n_tiles] as usize;
    // Key: depth's f32 bit pattern (monotonic for positive floats) above the index.
    let cursor: Vec<AtomicU32> = tile_start[..n_tiles]
        .iter()
        .map(|&s| AtomicU32::new(s))
        .collect();
    let slots: Vec<AtomicU64> = (0..total).map(|_| AtomicU64::new(0)).collect();
    rects
        .par_iter()
        .enumerate()
        .with_min_len(4096)
        .for_each(|(i, r)| {
            if rect_area(r) == 0 {
                return;
            }
            #[allow(clippy::unnecessary_cast)] // Real may be f64
            let key = ((splats[i].depth as f32).to_bits() as u64) << 32 | i as u64;
            for_each_tile(grid, r, |t| {
                let c = cursor[t].fetch_add(1, Ordering::Relaxed);
                slots[c as usize].store(key, Ordering::Relaxed);
            })
        });
    let mut keys: Vec<u64> = slots.into_iter().map(AtomicU64::into_inner).collect();
    let mut slices = Vec::with_capacity(n_tiles);
    let mut rest = keys.as_mut_slice();
    for t in 0..n_tiles {
        let (head, tail) = rest.split_at_mut((tile_start[t + 1] - tile_start[t]) as usize);
        slices.push(head);
        rest = tail;
    }
    slices.into_par_iter().for_each(|s| s.sort_unstable());
    let pair_gauss = keys.par_iter().map(|k| *k as u32).collect();
    Bins {
        tile_start,
        pair_gauss,
    }
}
