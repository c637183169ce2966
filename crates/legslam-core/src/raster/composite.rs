//! Front-to-back compositing of one tile, eight pixels of a row at a time, written once over
//! [`Lanes`] and run by the portable or the AVX2 implementation. [`cover`] is the one place that
//! decides which pixels a Gaussian covers and how much: the backward pass calls it too, or reads
//! back what it computed ([`cover_kept`]), so that both passes make the same decisions, bit for
//! bit.

use super::forward::Splat;
use super::lanes::{Lanes, LANES};
use super::tiles::Grid;
use super::{RasterConfig, TILE};
use crate::prefetch::prefetch;
use crate::Real;

/// Pixels of a tile.
pub(crate) const TILE_PIXELS: usize = TILE * TILE;
/// Per-pixel arrays of a tile are this long: a group of eight that starts near a row's end
/// reads (and writes back unchanged) the lanes beyond it.
pub(crate) const TILE_LANES: usize = TILE_PIXELS + LANES;

/// The pixels [x0, x_end) x [y0, y_end) of a tile.
#[derive(Clone, Copy, Debug)]
pub(crate) struct TileRect {
    pub x0: usize,
    pub y0: usize,
    pub x_end: usize,
    pub y_end: usize,
}

impl TileRect {
    pub fn new(grid: &Grid, t: usize, width: usize, height: usize) -> Self {
        let (x0, y0) = ((t % grid.tiles_x) * TILE, (t / grid.tiles_x) * TILE);
        TileRect {
            x0,
            y0,
            x_end: (x0 + TILE).min(width),
            y_end: (y0 + TILE).min(height),
        }
    }

    /// The x coordinates of the tile's columns and beyond, loaded eight at a time.
    pub fn columns(&self) -> [Real; TILE + LANES] {
        std::array::from_fn(|i| (self.x0 + i) as Real)
    }
}

/// One Gaussian over eight pixels of a row.
pub(crate) struct Cover<L: Lanes> {
    /// Lanes inside the row's span whose alpha reaches `alpha_min`.
    pub ok: L::Mask,
    /// Alpha, capped at `alpha_max`.
    pub alpha: L,
    /// exp(-sigma): d(alpha)/d(opacity) where alpha is not capped.
    pub falloff: L,
    pub dx: L,
    /// Lanes where alpha was capped (its gradient is then zero).
    pub capped: L::Mask,
}

/// Gaussian `s` at the pixels `px` of row `y` whose x lies in [lo, hi) (the row's span),
/// among the lanes `open` (the pixels still compositing; the others are never `ok`).
#[inline(always)]
pub(crate) fn cover<L: Lanes>(
    s: &Splat,
    y: usize,
    px: L,
    lo: Real,
    hi: Real,
    open: L::Mask,
    cfg: &RasterConfig,
) -> Cover<L> {
    let dy = y as Real - s.xy.y;
    let zero = L::splat(0.0);
    let inside = L::and_not(px.lt(L::splat(hi)), px.lt(L::splat(lo)));
    let dx = px.sub(L::splat(s.xy.x));
    let sigma = L::splat(0.5)
        .mul(
            L::splat(s.conic.x)
                .mul(dx)
                .mul(dx)
                .add(L::splat(s.conic.z * dy * dy)),
        )
        .add(L::splat(s.conic.y * dy).mul(dx));
    // Beyond the cut-off ellipse the alpha test would fail anyway; the margin leaves the exact
    // decision on the ellipse's rim to the alpha test.
    let in_ellipse = L::and_not(sigma.le(L::splat(s.sigma_max + 1e-3)), sigma.lt(zero));
    let candidates = L::and(L::and(inside, in_ellipse), open);
    if L::bits(candidates) == 0 {
        // No lane can pass the alpha test (the rows of a small Gaussian's bounding box often
        // miss its ellipse, and deep in a tile's list most pixels have stopped): every caller
        // skips a group without `ok` lanes, so the exponential, the costliest step here, is
        // not needed.
        return Cover {
            ok: candidates,
            alpha: zero,
            falloff: zero,
            dx,
            capped: candidates,
        };
    }
    let falloff = zero.sub(sigma).exp();
    let raw = L::splat(s.opacity).mul(falloff);
    let ok = L::and_not(candidates, raw.lt(L::splat(cfg.alpha_min)));
    Cover {
        ok,
        alpha: raw.min(L::splat(cfg.alpha_max)),
        falloff,
        dx,
        capped: raw.gt(L::splat(cfg.alpha_max)),
    }
}

/// [`cover`] from the falloff the forward pass kept for the group (zero in the lanes it did
/// not cover, whose raw alpha then falls below `alpha_min`, which is positive): the same
/// decisions and values in the lanes `open`, without the exponential.
#[inline(always)]
pub(crate) fn cover_kept<L: Lanes>(
    s: &Splat,
    px: L,
    falloff: L,
    open: L::Mask,
    cfg: &RasterConfig,
) -> Cover<L> {
    let raw = L::splat(s.opacity).mul(falloff);
    Cover {
        ok: L::and(L::splat(cfg.alpha_min).le(raw), open),
        alpha: raw.min(L::splat(cfg.alpha_max)),
        falloff,
        dx: px.sub(L::splat(s.xy.x)),
        capped: raw.gt(L::splat(cfg.alpha_max)),
    }
}

/// Eight consecutive pixels of a row, from a column of the tile that a Gaussian's extent
/// reaches; lanes past its extent (or the tile) are masked out.
#[derive(Clone, Copy)]
pub(crate) struct Group {
    pub y: usize,
    /// Tile-local index of the first pixel, and its column within the tile.
    pub lp: usize,
    pub gx: usize,
    /// The columns [lo, hi) of the extent within the tile.
    pub lo: Real,
    pub hi: Real,
}

impl Group {
    /// Gaussian `s` over the group's pixels (`cols`: [`TileRect::columns`]) that are `open`.
    #[inline(always)]
    pub fn cover<L: Lanes>(
        &self,
        s: &Splat,
        cols: &[Real; TILE + LANES],
        open: L::Mask,
        cfg: &RasterConfig,
    ) -> Cover<L> {
        cover(
            s,
            self.y,
            L::load(&cols[self.gx..]),
            self.lo,
            self.hi,
            open,
            cfg,
        )
    }
}

/// Calls `f` for each group of eight pixels that covers Gaussian `s`'s extent in tile `r`, row
/// by row, starting at the extent's first column (a Gaussian a few pixels wide takes one group
/// a row).
#[inline(always)]
pub(crate) fn for_each_group(s: &Splat, r: &TileRect, mut f: impl FnMut(Group)) {
    let columns = s.columns(r.x0, r.x_end);
    if columns.is_empty() {
        return;
    }
    let (lo, hi) = (columns.start as Real, columns.end as Real);
    for y in s.rows(r.y0, r.y_end) {
        let mut gx = columns.start - r.x0;
        while gx < columns.end - r.x0 {
            let lp = (y - r.y0) * TILE + gx;
            f(Group { y, lp, gx, lo, hi });
            gx += LANES;
        }
    }
}

/// How many groups [`for_each_group`] calls for Gaussian `s` in tile `r` (at most two a row).
#[inline(always)]
fn group_count(s: &Splat, r: &TileRect) -> usize {
    s.rows(r.y0, r.y_end).len() * s.columns(r.x0, r.x_end).len().div_ceil(LANES)
}

/// How many Gaussians of a tile's list ahead to prefetch: the lists reach splats and features
/// in no particular order, and a miss would stall the walk.
pub(crate) const PREFETCH: usize = 8;

/// Asks the cache for Gaussian `gi`'s splat and features.
#[inline(always)]
pub(crate) fn prefetch_gaussian(gi: u32, splats: &[Splat], features: &[Real], k: usize) {
    let gi = gi as usize;
    prefetch(std::slice::from_ref(&splats[gi]));
    prefetch(&features[gi * k..][..k]);
}

/// The pixels of a tile still compositing: a bit per column, a word per row. Deep in a list
/// most of a Gaussian's pixels have stopped, and the forward pass skips (and does not
/// prefetch the features of) a Gaussian none of whose pixels is open.
struct OpenPixels([u32; TILE]);

impl OpenPixels {
    fn new(r: &TileRect) -> Self {
        let row = (1u32 << (r.x_end - r.x0)) - 1;
        OpenPixels(std::array::from_fn(|y| {
            if y < r.y_end - r.y0 {
                row
            } else {
                0
            }
        }))
    }

    /// Whether a pixel of `s`'s extent in tile `r` is open (none is where the extent misses
    /// the tile's pixels).
    #[inline(always)]
    fn any(&self, s: &Splat, r: &TileRect) -> bool {
        let cols = s.columns(r.x0, r.x_end);
        if cols.is_empty() {
            return false;
        }
        let below = |c: usize| (1u32 << (c - r.x0)) - 1;
        let mask = below(cols.end) & !below(cols.start);
        s.rows(r.y0, r.y_end).any(|y| self.0[y - r.y0] & mask != 0)
    }

    /// Closes the lanes `bits` of the group that starts at tile-local pixel `lp`.
    #[inline(always)]
    fn close(&mut self, lp: usize, bits: u32) {
        self.0[lp / TILE] &= !(bits << (lp % TILE));
    }
}

/// Per-pixel accumulators of one tile, structure of arrays, indexed (y - y0) * TILE + (x - x0).
pub(crate) struct TileAcc {
    pub trans: [Real; TILE_LANES],
    pub color: [[Real; TILE_LANES]; 3],
    pub depth: [Real; TILE_LANES],
    /// 1 where the pixel has stopped compositing.
    done: [Real; TILE_LANES],
    /// The last contributor's position in the tile's list, + 1.
    pub end: [u32; TILE_LANES],
    active: usize,
}

impl TileAcc {
    pub fn new() -> Self {
        TileAcc {
            trans: [1.0; TILE_LANES],
            color: [[0.0; TILE_LANES]; 3],
            depth: [0.0; TILE_LANES],
            done: [0.0; TILE_LANES],
            end: [0; TILE_LANES],
            active: 0,
        }
    }

    /// Back to an empty tile whose `pixels` pixels all composite.
    pub fn reset(&mut self, pixels: usize) {
        self.trans.fill(1.0);
        self.color.iter_mut().for_each(|c| c.fill(0.0));
        self.depth.fill(0.0);
        self.done.fill(0.0);
        self.end.fill(0);
        self.active = pixels;
    }
}

/// What compositing every tile of one layer reads.
#[derive(Clone, Copy)]
pub(crate) struct TileInputs<'a> {
    pub splats: &'a [Splat],
    /// The Gaussians' features, [N, k].
    pub features: &'a [Real],
    /// Feature channels the layer composites.
    pub k: usize,
    /// Whether the layer accumulates colour and depth (the features' own layer has none).
    pub colour: bool,
    pub cfg: &'a RasterConfig,
    /// The layer's width in pixels.
    pub width: usize,
}

/// What compositing a tile writes besides its accumulators.
pub(crate) struct TileOut<'a, 'b> {
    /// The rows of the layer's feature image from the tile's first, [rows, width, k] (zero
    /// where the tile lies).
    pub feat: &'a mut [Real],
    /// Per entry of the tile's list: whether the Gaussian added to one of its pixels.
    pub added: &'a mut [bool],
    /// Where each group's exponential is kept (zero in the lanes not covered), for
    /// [`cover_kept`]: of the Gaussians that added to a pixel only, as the backward pass walks
    /// no others.
    pub falloffs: Option<&'a mut KeptFalloffs<'b>>,
}

/// A row of tiles' kept falloffs, written at a cursor into a buffer that only grows: pushed
/// onto a vector instead, each group's store waited on the vector's length, stored and
/// loaded back (7% of the forward's samples).
pub(crate) struct KeptFalloffs<'a> {
    buf: &'a mut Vec<Real>,
    /// Where the next group goes: the row's falloffs are `buf[..at]`.
    pub at: usize,
}

impl<'a> KeptFalloffs<'a> {
    /// A row's falloffs from the start of `buf` (whatever it holds beyond them is stale).
    pub fn new(buf: &'a mut Vec<Real>) -> Self {
        KeptFalloffs { buf, at: 0 }
    }

    /// The next `len` values, for the caller to fill before it advances `at` over them.
    #[inline(always)]
    fn room(&mut self, len: usize) -> &mut [Real] {
        let end = self.at + len;
        // Grown only as far as used, so that no more memory is touched than the falloffs
        // take (the capacity still grows geometrically).
        if self.buf.len() < end {
            self.buf.resize(end, 0.0);
        }
        &mut self.buf[self.at..end]
    }
}

/// Composites the tile's list `list` (front to back) into `acc` and `out`: Gaussian-major, so
/// that only the pixels inside each Gaussian's span are visited, eight at a time; every pixel
/// still sees its Gaussians in depth order.
#[inline(always)]
pub(crate) fn composite<L: Lanes>(
    acc: &mut TileAcc,
    inputs: &TileInputs,
    list: &[u32],
    r: &TileRect,
    out: TileOut,
) {
    if inputs.colour {
        composite_with::<L, true>(acc, inputs, list, r, out)
    } else {
        composite_with::<L, false>(acc, inputs, list, r, out)
    }
}

/// [`composite`], compiled with colour and depth or without.
#[inline(always)]
fn composite_with<L: Lanes, const COLOUR: bool>(
    acc: &mut TileAcc,
    inputs: &TileInputs,
    list: &[u32],
    r: &TileRect,
    out: TileOut,
) {
    let TileInputs {
        splats,
        features,
        k,
        cfg,
        width,
        ..
    } = *inputs;
    let TileOut {
        feat,
        added,
        mut falloffs,
    } = out;
    added.fill(false);
    let cols = r.columns();
    let (zero, one) = (L::splat(0.0), L::splat(1.0));
    let t_min = L::splat(cfg.transmittance_min);
    let mut open = OpenPixels::new(r);
    for (j, &gi) in list.iter().enumerate() {
        // The splats two distances ahead, and one distance ahead, once its splat has come,
        // the features of a Gaussian that can still add.
        if let Some(&far) = list.get(j + 2 * PREFETCH) {
            prefetch(std::slice::from_ref(&splats[far as usize]));
        }
        if let Some(&near) = list.get(j + PREFETCH) {
            if k > 0 && open.any(&splats[near as usize], r) {
                prefetch(&features[near as usize * k..][..k]);
            }
        }
        let s = &splats[gi as usize];
        if !open.any(s, r) {
            continue;
        }
        let f = &features[gi as usize * k..][..k];
        // Not `array::map`, which is not always inlined into the AVX2 kernel (see `walk_tile`).
        let color = [
            L::splat(s.color.x),
            L::splat(s.color.y),
            L::splat(s.color.z),
        ];
        let depth = L::splat(s.depth);
        // Room for every group of the pair.
        let mut room = falloffs
            .as_mut()
            .map(|kept| kept.room(group_count(s, r) * LANES));
        let mut used = 0;
        let mut any = false;
        for_each_group(s, r, |g| {
            let lp = g.lp;
            // Pixels that have stopped are left out before the exponential. The falloffs
            // kept are then zero there too, where the backward pass never looks (the pixel's
            // list ended before this Gaussian).
            let done = L::load(&acc.done[lp..]);
            let c = g.cover::<L>(s, &cols, done.le(zero), cfg);
            if let Some(room) = room.as_deref_mut() {
                L::select(c.ok, c.falloff, zero).store(&mut room[used..]);
                used += LANES;
            }
            let live = c.ok;
            if L::bits(live) == 0 {
                return;
            }
            let t = L::load(&acc.trans[lp..]);
            let next = t.mul(one.sub(c.alpha));
            let stop = L::and(live, next.lt(t_min));
            let add = L::and_not(live, stop);
            let stopped = L::bits(stop);
            if stopped != 0 {
                open.close(lp, stopped);
                one.store_where(stop, done, &mut acc.done[lp..]);
                acc.active -= stopped.count_ones() as usize;
            }
            any |= L::bits(add) != 0;
            let wgt = L::select(add, c.alpha.mul(t), zero);
            if COLOUR {
                for (ch, v) in acc.color.iter_mut().zip(color) {
                    L::load(&ch[lp..]).add(wgt.mul(v)).store(&mut ch[lp..]);
                }
                L::load(&acc.depth[lp..])
                    .add(wgt.mul(depth))
                    .store(&mut acc.depth[lp..]);
            }
            next.store_where(add, t, &mut acc.trans[lp..]);
            L::set_where(add, j as u32 + 1, &mut acc.end[lp..]);
            if k > 0 {
                let mut w = [0.0; LANES];
                wgt.store(&mut w);
                let mut bits = L::bits(add);
                let p0 = (g.y - r.y0) * width + r.x0 + g.gx;
                while bits != 0 {
                    let l = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    L::axpy(&mut feat[(p0 + l) * k..][..k], w[l], f);
                }
            }
        });
        added[j] = any;
        if any {
            if let Some(kept) = falloffs.as_mut() {
                kept.at += used;
            }
        }
        if acc.active == 0 {
            break;
        }
    }
}
