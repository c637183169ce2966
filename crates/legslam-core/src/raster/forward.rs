//! Forward pass: project every Gaussian, bin into tiles, composite front to back.

use rayon::prelude::*;

use super::composite::{composite, TileAcc, TileRect};
#[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
use super::lanes::Avx2;
use super::lanes::{Portable, Simd};
use super::math::{sigmoid, V2, V3};
use super::project::{color_raw, extent, extent_bound, geometry, Pinhole};
use super::tiles::{bin, rect, rect_area, Bins, Grid, Rect};
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

/// The integer coordinates in [c - e, c + e], clipped to [0, size), as [first, end).
#[inline]
fn pixel_span(c: Real, e: Real, size: usize) -> [u32; 2] {
    let first = (c - e).ceil().max(0.0).min(size as Real) as u32;
    let end = ((c + e).floor() + 1.0).max(0.0).min(size as Real) as u32;
    [first, end.max(first)]
}

/// What the backward pass needs from the forward pass.
#[derive(Clone, Debug, Default)]
pub(crate) struct State {
    pub grid: Grid,
    pub splats: Vec<Splat>,
    pub rects: Vec<Rect>,
    pub bins: Bins,
    /// Per pixel: how many entries of its tile's list were walked (the last contributor + 1).
    pub pixel_end: Vec<u32>,
    /// Per pixel: final transmittance.
    pub pixel_t: Vec<Real>,
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
    let grid = Grid::new(w, h);
    let st = &mut out.state;
    project_all(g, cam, opts, &grid, st, &mut out.radii);
    st.bins = bin(&grid, &st.rects, &st.splats);
    st.grid = grid;
    st.options = RenderOptions { simd, ..*opts };

    // Compositing, one row of tiles at a time (its pixels are contiguous in every image).
    let npix = w * h;
    let sized = |v: &mut Vec<Real>, on: bool, len: usize| {
        v.clear();
        v.resize(if on { len } else { 0 }, 0.0);
    };
    sized(&mut out.color, opts.color, npix * 3);
    sized(&mut out.depth, opts.depth, npix);
    sized(&mut out.alpha, opts.alpha, npix);
    sized(&mut out.features, k > 0, npix * k);
    st.pixel_end.resize(npix, 0);
    st.pixel_t.resize(npix, 0.0);
    let rows = TILE * w;
    let n = grid.tiles_y;
    let outs: Vec<_> = split_chunks(&mut out.color, rows * 3, n)
        .into_iter()
        .zip(split_chunks(&mut out.depth, rows, n))
        .zip(split_chunks(&mut out.alpha, rows, n))
        .zip(split_chunks(&mut out.features, rows * k, n))
        .zip(split_chunks(&mut st.pixel_end, rows, n))
        .zip(split_chunks(&mut st.pixel_t, rows, n))
        .enumerate()
        .collect();
    let (bins, splats, cfg) = (&st.bins, &st.splats[..], &opts.config);
    outs.into_par_iter()
        .for_each(|(ty, (((((col, dep), alp), fea), end), tr))| {
            let mut acc = TileAcc::new(k);
            for tx in 0..grid.tiles_x {
                let t = ty * grid.tiles_x + tx;
                let r = TileRect::new(&grid, t, w, h);
                let list = bins.list(t);
                acc.reset((r.x_end - r.x0) * (r.y_end - r.y0));
                if !list.is_empty() {
                    composite_tile(simd, &mut acc, list, splats, g.features, k, &r, cfg);
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
                        if k > 0 {
                            fea[p * k..][..k].copy_from_slice(&acc.feat[lp * k..][..k]);
                        }
                        end[p] = acc.end[lp];
                        tr[p] = acc.trans[lp];
                    }
                }
            }
        });
    out.width = w;
    out.height = h;
    out.num_features = k;
    Ok(())
}

/// Projects every Gaussian into `st.splats` and `st.rects` (culled ones get an empty rect) and
/// their screen radii into `radii`.
fn project_all(
    g: &Gaussians,
    cam: &Camera,
    opts: &RenderOptions,
    grid: &Grid,
    st: &mut State,
    radii: &mut Vec<Real>,
) {
    let cfg = &opts.config;
    let pin = Pinhole::new(cam, cfg);
    let cam_pos = cam.position();
    let (image_w, image_h) = (cam.intrinsics.width, cam.intrinsics.height);
    let n = g.len();
    st.splats.resize(n, Splat::default());
    st.rects.resize(n, [0; 4]);
    radii.resize(n, 0.0);
    st.splats
        .par_iter_mut()
        .zip(st.rects.par_iter_mut())
        .zip(radii.par_iter_mut())
        .enumerate()
        .with_min_len(1024)
        .for_each(|(i, ((splat, rect), radius))| {
            *rect = [0; 4];
            *radius = 0.0;
            let opacity = sigmoid(g.opacity_logits[i]);
            // Most of a large map lies outside any one view: rule those out before the full
            // projection.
            match extent_bound(g, i, cam, &pin, opacity, cfg) {
                Some((xy, e)) if rect_area(&rect_of(grid, xy, e)) > 0 => {}
                _ => return,
            }
            let Some(geo) = geometry(g, i, cam, &pin, cfg) else {
                return;
            };
            let Some(ext) = extent(&geo, opacity, cfg) else {
                return;
            };
            let r = rect_of(grid, geo.xy, ext);
            if rect_area(&r) == 0 {
                return;
            }
            let color = if opts.color {
                color_raw(g, i, opts.sh_degree, cam_pos).max(V3::ZERO)
            } else {
                V3::ZERO
            };
            *splat = Splat {
                xy: geo.xy,
                conic: geo.conic,
                opacity,
                depth: geo.p_cam.z,
                color,
                pixels: {
                    let ([x0, x1], [y0, y1]) = (
                        pixel_span(geo.xy.x, ext.x, image_w),
                        pixel_span(geo.xy.y, ext.y, image_h),
                    );
                    [x0, y0, x1, y1]
                },
                sigma_max: (opacity / cfg.alpha_min).ln(),
            };
            *rect = r;
            *radius = ext.x.max(ext.y);
        });
}

#[inline]
fn rect_of(grid: &Grid, xy: V2, ext: V2) -> Rect {
    rect(grid, xy.x, xy.y, ext.x, ext.y)
}

/// One tile through the implementation `simd` chose.
#[allow(clippy::too_many_arguments)]
fn composite_tile(
    simd: Simd,
    acc: &mut TileAcc,
    list: &[u32],
    splats: &[Splat],
    features: &[Real],
    k: usize,
    r: &TileRect,
    cfg: &RasterConfig,
) {
    #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
    if simd == Simd::Avx2 {
        // SAFETY: `Simd::resolve` chose AVX2 only where the CPU has it.
        return unsafe { composite_avx2(acc, list, splats, features, k, r, cfg) };
    }
    let _ = simd;
    composite::<Portable>(acc, list, splats, features, k, r, cfg)
}

/// [`composite`] compiled with AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
#[target_feature(enable = "avx2")]
#[allow(clippy::too_many_arguments)]
unsafe fn composite_avx2(
    acc: &mut TileAcc,
    list: &[u32],
    splats: &[Splat],
    features: &[Real],
    k: usize,
    r: &TileRect,
    cfg: &RasterConfig,
) {
    composite::<Avx2>(acc, list, splats, features, k, r, cfg)
}
