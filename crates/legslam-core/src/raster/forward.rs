//! Forward pass: project every Gaussian, bin into tiles, composite front to back. Colour,
//! depth and alpha composite in the main layer; features either there too or, when asked for
//! at a coarser scale, in a layer of their own whose splats come from the same projection.

use rayon::prelude::*;

use super::composite::{composite, KeptFalloffs, TileAcc, TileInputs, TileOut, TileRect};
use super::lanes::{dispatch, Simd};
use super::math::{V2, V3};
use super::project;
use super::tiles::{bin, Bins, Grid, Rect};
use super::{Camera, Gaussians, RasterConfig, RenderOptions, Rendered, TILE};
use crate::Real;

/// A projected Gaussian, as the compositing loops read it: one cache line each, since the
/// tiles' lists reach them in no particular order.
#[derive(Clone, Copy, Debug, Default)]
#[repr(align(64))]
pub(crate) struct Splat {
    pub xy: V2,
    /// Inverse 2D covariance entries (a, b, c): sigma = 0.5 (a dx^2 + c dy^2) + b dx dy.
    pub conic: V3,
    pub opacity: Real,
    pub depth: Real,
    pub color: V3,
    /// The pixels [x0, x1) x [y0, y1) of the image within the Gaussian's extent (the region
    /// where its alpha can reach `alpha_min`), so that a tile clips integers.
    pub pixels: [u32; 4],
    /// ln(opacity / alpha_min): where sigma exceeds it, alpha is below the cut-off.
    pub sigma_max: Real,
}

impl Splat {
    /// Rows of the tile [y0, y_end) that the Gaussian's extent reaches.
    #[inline(always)]
    pub fn rows(&self, y0: usize, y_end: usize) -> std::ops::Range<usize> {
        clip(self.pixels[1], self.pixels[3], y0, y_end)
    }

    /// Columns of the tile [x0, x_end) that the Gaussian's extent reaches.
    #[inline(always)]
    pub fn columns(&self, x0: usize, x_end: usize) -> std::ops::Range<usize> {
        clip(self.pixels[0], self.pixels[2], x0, x_end)
    }
}

/// [lo, hi) within [start, end) (empty when they do not meet).
#[inline(always)]
fn clip(lo: u32, hi: u32, start: usize, end: usize) -> std::ops::Range<usize> {
    let first = (lo as usize).max(start);
    first..(hi as usize).min(end).max(first)
}

/// One compositing layer of a render: its size, splats, tile lists and what each pixel did.
#[derive(Clone, Debug, Default)]
pub(crate) struct Layer {
    pub width: usize,
    pub height: usize,
    pub grid: Grid,
    pub splats: Vec<Splat>,
    pub rects: Vec<Rect>,
    pub bins: Bins,
    /// Per pixel: how many entries of its tile's list were walked (the last contributor + 1).
    pub pixel_end: Vec<u32>,
    /// Per pixel: final transmittance.
    pub pixel_t: Vec<Real>,
    /// Per row of tiles, the falloff exp(-sigma) of every group of eight pixels its tiles
    /// walked, in walking order (zero where a lane was not covered), when the render was made
    /// `for_backward` (empty otherwise): the backward pass reads them instead of evaluating the
    /// exponential again. Past the row's last group, stale values of an earlier render.
    pub falloffs: Vec<Vec<Real>>,
    /// Per tile, where its groups start in its row's `falloffs`.
    pub falloff_start: Vec<usize>,
    /// Per pair (entry of `bins.pair_gauss`): whether the Gaussian added to a pixel of the
    /// tile. The others (a third of the features' layer's pairs: an ellipse between pixel
    /// centres, pixels already opaque) have no gradient, and the backward pass skips them.
    pub added: Vec<bool>,
}

impl Layer {
    fn reset(&mut self, width: usize, height: usize, n: usize) {
        self.width = width;
        self.height = height;
        self.grid = Grid::new(width, height);
        self.splats.resize(n, Splat::default());
        self.rects.resize(n, [0; 4]);
    }

    fn clear(&mut self) {
        *self = Layer {
            splats: std::mem::take(&mut self.splats),
            rects: std::mem::take(&mut self.rects),
            falloffs: std::mem::take(&mut self.falloffs),
            ..Default::default()
        };
        self.splats.clear();
        self.rects.clear();
    }
}

/// What the backward pass needs from the forward pass.
#[derive(Clone, Debug, Default)]
pub(crate) struct State {
    /// Colour, depth, alpha, and the features unless they have a layer of their own.
    pub main: Layer,
    /// The features alone, `feature_scale` times coarser (empty at scale 1).
    pub coarse: Layer,
    /// Per Gaussian, its depth's f32 bits, the key both layers' tile lists are sorted by:
    /// binning reads these 4 bytes a Gaussian, not a splat's cache line.
    pub depth_keys: Vec<u32>,
    pub options: RenderOptions,
}

/// Splits `v` into `n` consecutive slices of `len` elements (the last may be shorter), or `n`
/// empty slices when `v` is empty (an output that was not requested).
pub(crate) fn split_chunks<T>(v: &mut [T], len: usize, n: usize) -> Vec<&mut [T]> {
    if v.is_empty() {
        return (0..n).map(|_| <&mut [T]>::default()).collect();
    }
    v.chunks_mut(len.max(1)).collect()
}

/// Renders the requested images. Does not validate the Gaussians (see
/// [`Gaussians::validate`]): the engine's own loops pass arrays they maintain.
pub fn render(g: &Gaussians, cam: &Camera, opts: &RenderOptions) -> Result<Rendered, String> {
    let mut out = Rendered::default();
    render_into(g, cam, opts, &mut out)?;
    Ok(out)
}

/// [`render`] into `out`, reusing its buffers (a training loop renders the same sizes again
/// and again; fresh buffers would page-fault over megabytes per call).
pub fn render_into(
    g: &Gaussians,
    cam: &Camera,
    opts: &RenderOptions,
    out: &mut Rendered,
) -> Result<(), String> {
    opts.config.validate()?;
    cam.intrinsics.validate()?;
    let simd = opts.simd.resolve()?;
    let max_degree = (g.sh_coeffs as f64).sqrt() as usize - 1;
    if opts.color && opts.sh_degree > max_degree {
        return Err(format!(
            "sh_degree {} needs {} coefficients per channel, the Gaussians have {}",
            opts.sh_degree,
            super::sh::num_coeffs(opts.sh_degree),
            g.sh_coeffs
        ));
    }
    let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
    let k = if opts.features { g.num_features } else { 0 };
    let scale = opts.feature_scale;
    if scale == 0 || (k > 0 && (w < scale || h < scale)) {
        return Err(format!(
            "feature_scale must be at least 1 and at most the image size, got {scale} for {w}x{h}"
        ));
    }
    if let Some(o) = opts
        .feature_origin
        .filter(|o| !o.iter().all(|v| v.is_finite()))
    {
        return Err(format!("feature_origin must be finite, got {o:?}"));
    }
    let coarse = k > 0 && scale > 1;
    let st = &mut out.state;
    st.main.reset(w, h, g.len());
    if coarse {
        st.coarse.reset(w / scale, h / scale, g.len());
    } else {
        st.coarse.clear();
    }
    let coarse_scale = coarse.then_some(scale);
    let (main, low) = (&mut st.main, &mut st.coarse);
    let keys = &mut st.depth_keys;
    project::project(
        g,
        cam,
        opts,
        simd,
        coarse_scale,
        main,
        low,
        keys,
        &mut out.radii,
    );
    st.options = RenderOptions { simd, ..*opts };
    let main_k = if coarse { 0 } else { k };
    // The compositing writes every pixel of each image it outputs, so a reused buffer is
    // resized, not cleared (64 features at 640x480 are 79 MB to zero).
    let outputs = |v: &mut Vec<Real>, on: bool, len: usize| {
        v.resize(if on { len } else { 0 }, 0.0);
    };
    outputs(&mut out.color, opts.color, w * h * 3);
    outputs(&mut out.depth, opts.depth, w * h);
    outputs(&mut out.alpha, opts.alpha, w * h);
    let (fw, fh) = if coarse {
        (w / scale, h / scale)
    } else {
        (w, h)
    };
    outputs(&mut out.features, k > 0, fw * fh * k);
    // The features go to the main layer's images, or to their own layer's.
    let (main_features, coarse_features) = if coarse {
        (&mut [][..], &mut out.features[..])
    } else {
        (&mut out.features[..], &mut [][..])
    };
    let images = Images {
        color: &mut out.color,
        depth: &mut out.depth,
        alpha: &mut out.alpha,
        features: main_features,
    };
    let keep = opts.for_backward;
    let cfg = &opts.config;
    let keys = &st.depth_keys;
    let main = || {
        composite_layer(
            &mut st.main,
            keys,
            simd,
            g.features,
            main_k,
            images,
            cfg,
            keep,
        )
    };
    if coarse {
        let images = Images {
            color: &mut [],
            depth: &mut [],
            alpha: &mut [],
            features: coarse_features,
        };
        let cfg = &cfg.for_features();
        // Side by side: either layer alone has too few rows of tiles to keep both threads
        // busy to its end (the features' 160x120 has eight).
        rayon::join(main, || {
            composite_layer(&mut st.coarse, keys, simd, g.features, k, images, cfg, keep)
        });
    } else {
        main();
    }
    out.width = w;
    out.height = h;
    out.num_features = k;
    out.feature_width = fw;
    out.feature_height = fh;
    Ok(())
}

/// The images a layer composites into (empty slices for those not requested).
struct Images<'a> {
    color: &'a mut [Real],
    depth: &'a mut [Real],
    alpha: &'a mut [Real],
    features: &'a mut [Real],
}

/// Bins a projected layer (by `depth_keys`) and composites it, one row of tiles at a time (its
/// pixels are contiguous in every image), `k` feature channels of `features` ([N, k]); with
/// `keep`, keeps the falloffs for the backward pass.
#[allow(clippy::too_many_arguments)]
fn composite_layer(
    layer: &mut Layer,
    depth_keys: &[u32],
    simd: Simd,
    features: &[Real],
    k: usize,
    images: Images,
    cfg: &RasterConfig,
    keep: bool,
) {
    let (w, h, grid) = (layer.width, layer.height, layer.grid);
    bin(&grid, &layer.rects, depth_keys, &mut layer.bins);
    layer.pixel_end.resize(w * h, 0);
    layer.pixel_t.resize(w * h, 0.0);
    // Rows are only ever added: a training loop alternates pyramid levels, and a row dropped
    // would be grown again, a page fault at a time.
    if layer.falloffs.len() < grid.tiles_y {
        layer.falloffs.resize_with(grid.tiles_y, Vec::new);
    }
    layer.falloff_start.resize(grid.len(), 0);
    layer.added.resize(layer.bins.pair_gauss.len(), false);
    let rows = TILE * w;
    let n = grid.tiles_y;
    // Colour and depth are accumulated only where they are output.
    let colour = !images.color.is_empty() || !images.depth.is_empty();
    let outs: Vec<_> = split_chunks(images.color, rows * 3, n)
        .into_iter()
        .zip(split_chunks(images.depth, rows, n))
        .zip(split_chunks(images.alpha, rows, n))
        .zip(split_chunks(images.features, rows * k, n))
        .zip(split_chunks(&mut layer.pixel_end, rows, n))
        .zip(split_chunks(&mut layer.pixel_t, rows, n))
        .zip(layer.falloffs.iter_mut())
        .zip(layer.falloff_start.chunks_mut(grid.tiles_x))
        .zip(split_rows(&mut layer.added, &layer.bins, &grid))
        .enumerate()
        .collect();
    let bins = &layer.bins;
    let inputs = TileInputs {
        splats: &layer.splats,
        features,
        k,
        colour,
        cfg,
        width: w,
    };
    outs.into_par_iter().for_each(
        |(ty, ((((((((col, dep), alp), fea), end), tr), fo), starts), added))| {
            let mut acc = TileAcc::new();
            let mut kept = KeptFalloffs::new(fo);
            let row_start = bins.tile_start[ty * grid.tiles_x] as usize;
            for (tx, start) in starts.iter_mut().enumerate() {
                let t = ty * grid.tiles_x + tx;
                let r = TileRect::new(&grid, t, w, h);
                let list = bins.list(t);
                acc.reset((r.x_end - r.x0) * (r.y_end - r.y0));
                *start = kept.at;
                // The features accumulate in the image itself (a tile's own buffer cost a
                // 64 kB copy a tile at K = 64).
                if k > 0 {
                    for y in 0..r.y_end - r.y0 {
                        fea[(y * w + r.x0) * k..(y * w + r.x_end) * k].fill(0.0);
                    }
                }
                if !list.is_empty() {
                    let out = TileOut {
                        feat: &mut *fea,
                        added: &mut added[bins.tile_start[t] as usize - row_start..][..list.len()],
                        falloffs: keep.then_some(&mut kept),
                    };
                    composite_tile(simd, &mut acc, &inputs, list, &r, out);
                }
                for y in r.y0..r.y_end {
                    for x in r.x0..r.x_end {
                        let lp = (y - r.y0) * TILE + (x - r.x0);
                        let p = (y - r.y0) * w + x;
                        if !col.is_empty() {
                            for c in 0..3 {
                                col[3 * p + c] = acc.color[c][lp];
                            }
                        }
                        if !dep.is_empty() {
                            dep[p] = acc.depth[lp];
                        }
                        if !alp.is_empty() {
                            alp[p] = 1.0 - acc.trans[lp];
                        }
                        end[p] = acc.end[lp];
                        tr[p] = acc.trans[lp];
                    }
                }
            }
        },
    );
}

/// Each row of tiles' part of the per-pair `flags` (a row's lists are consecutive).
fn split_rows<'a>(flags: &'a mut [bool], bins: &Bins, grid: &Grid) -> Vec<&'a mut [bool]> {
    let mut rest = flags;
    (0..grid.tiles_y)
        .map(|ty| {
            let at = |ty: usize| bins.tile_start[ty * grid.tiles_x] as usize;
            let (row, tail) = std::mem::take(&mut rest).split_at_mut(at(ty + 1) - at(ty));
            rest = tail;
            row
        })
        .collect()
}

/// One tile through the implementation `simd` chose.
fn composite_tile(
    simd: Simd,
    acc: &mut TileAcc,
    inputs: &TileInputs,
    list: &[u32],
    r: &TileRect,
    out: TileOut,
) {
    dispatch!(
        simd,
        composite(
            acc: &mut TileAcc,
            inputs: &TileInputs,
            list: &[u32],
            r: &TileRect,
            out: TileOut,
        )
    )
}
