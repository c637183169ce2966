//! Forward pass: project every Gaussian, bin into tiles, composite front to back.

use rayon::prelude::*;

use super::math::{sigmoid, V2, V3};
use super::project::{color_raw, extent, extent_bound, geometry, Pinhole};
use super::tiles::{bin, rect, Bins, Grid, Rect};
use super::{Camera, Gaussians, RasterConfig, RenderOptions, Rendered, TILE};
use crate::Real;

/// A projected Gaussian, as the compositing loops read it.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Splat {
    pub xy: V2,
    /// Inverse 2D covariance entries (a, b, c): sigma = 0.5 (a dx^2 + c dy^2) + b dx dy.
    pub conic: V3,
    pub opacity: Real,
    pub depth: Real,
    pub color: V3,
    /// Half extents (x, y) in pixels of the region where alpha can reach `alpha_min`.
    pub ext: V2,
    /// ln(opacity / alpha_min): where sigma exceeds it, alpha is below the cut-off.
    pub sigma_max: Real,
}

impl Splat {
    /// Rows of the tile [y0, y_end) that the Gaussian's extent reaches.
    #[inline(always)]
    pub fn rows(&self, y0: usize, y_end: usize) -> std::ops::Range<usize> {
        span(self.xy.y - self.ext.y, self.xy.y + self.ext.y, y0, y_end)
    }

    /// Pixels of row `y` within [x0, x_end) inside the cut-off ellipse
    /// 0.5 d^T conic d <= sigma_max (widened a hair, so that the alpha test stays the one
    /// exact decision): solving the quadratic in dx skips the bounding box's empty corners.
    #[inline(always)]
    pub fn row_span(&self, y: usize, x0: usize, x_end: usize) -> std::ops::Range<usize> {
        let (a, b, c) = (self.conic.x, self.conic.y, self.conic.z);
        let dy = y as Real - self.xy.y;
        let level = 2.0 * (self.sigma_max + 2e-3);
        let disc = (b * dy) * (b * dy) - a * (c * dy * dy - level);
        if disc.is_nan() || disc < 0.0 {
            return x0..x0;
        }
        let (mid, half) = (self.xy.x - b * dy / a, disc.sqrt() / a);
        span(mid - half - 1e-3, mid + half + 1e-3, x0, x_end)
    }
}

/// One Gaussian's alpha at one pixel, with what the backward pass needs of it.
pub(crate) struct AlphaAt {
    pub alpha: Real,
    /// exp(-sigma): d(alpha)/d(opacity) when not capped.
    pub falloff: Real,
    pub dx: Real,
    pub dy: Real,
    /// Whether alpha was capped at `alpha_max` (its gradient is then zero).
    pub capped: bool,
}

/// Integer coordinates in [lo, hi] clipped to [start, end).
#[inline(always)]
fn span(lo: Real, hi: Real, start: usize, end: usize) -> std::ops::Range<usize> {
    let first = lo.ceil().max(start as Real) as usize;
    let last = ((hi.floor() + 1.0).max(0.0) as usize).min(end);
    first.max(start)..last.max(first.max(start))
}

/// The one place that decides whether and how much a Gaussian covers a pixel; forward and
/// backward both call it so that their decisions agree exactly.
#[inline(always)]
pub(crate) fn alpha_at(s: &Splat, px: Real, py: Real, cfg: &RasterConfig) -> Option<AlphaAt> {
    let dx = px - s.xy.x;
    let dy = py - s.xy.y;
    let sigma = 0.5 * (s.conic.x * dx * dx + s.conic.z * dy * dy) + s.conic.y * dx * dy;
    // Beyond the cut-off ellipse (the bulk of a Gaussian's bounding box) skip the exp; the
    // margin leaves the exact decision on the ellipse's rim to the alpha test below.
    if sigma < 0.0 || sigma > s.sigma_max + 1e-3 {
        return None;
    }
    let falloff = (-sigma).exp();
    let raw = s.opacity * falloff;
    if raw < cfg.alpha_min {
        return None;
    }
    Some(AlphaAt {
        alpha: raw.min(cfg.alpha_max),
        falloff,
        dx,
        dy,
        capped: raw > cfg.alpha_max,
    })
}

/// What the backward pass needs from the forward pass.
#[derive(Clone, Debug)]
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
    opts.config.validate()?;
    cam.intrinsics.validate()?;
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
    let cfg = &opts.config;
    let pin = Pinhole::new(cam, cfg);
    let grid = Grid::new(w, h);
    let cam_pos = cam.position();

    // Projection, one Gaussian at a time.
    let projected: Vec<(Splat, Rect, Real)> = (0..g.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            let culled = (Splat::default(), [0; 4], 0.0);
            let opacity = sigmoid(g.opacity_logits[i]);
            // Most of a large map lies outside any one view: rule those out before the full
            // projection.
            match extent_bound(g, i, cam, &pin, opacity, cfg) {
                Some((xy, e)) => {
                    let r = rect(&grid, xy.x, xy.y, e.x, e.y);
                    if r[0] >= r[2] || r[1] >= r[3] {
                        return culled;
                    }
                }
                None => return culled,
            }
            let Some(geo) = geometry(g, i, cam, &pin, cfg) else {
                return culled;
            };
            let Some(ext) = extent(&geo, opacity, cfg) else {
                return culled;
            };
            let r = rect(&grid, geo.xy.x, geo.xy.y, ext.x, ext.y);
            if r[0] >= r[2] || r[1] >= r[3] {
                return culled;
            }
            let color = if opts.color {
                color_raw(g, i, opts.sh_degree, cam_pos).max(V3::ZERO)
            } else {
                V3::ZERO
            };
            let splat = Splat {
                xy: geo.xy,
                conic: geo.conic,
                opacity,
                depth: geo.p_cam.z,
                color,
                ext,
                sigma_max: (opacity / cfg.alpha_min).ln(),
            };
            (splat, r, ext.x.max(ext.y))
        })
        .collect();
    let mut splats = Vec::with_capacity(g.len());
    let mut rects = Vec::with_capacity(g.len());
    let mut radii = Vec::with_capacity(g.len());
    for (s, r, rad) in projected {
        splats.push(s);
        rects.push(r);
        radii.push(rad);
    }
    let depth_keys: Vec<Real> = splats.iter().map(|s| s.depth).collect();
    let bins = bin(&grid, &rects, &depth_keys);

    // Compositing, one row of tiles at a time (its pixels are contiguous in every image).
    let npix = w * h;
    let mut color = vec![0.0; if opts.color { npix * 3 } else { 0 }];
    let mut depth = vec![0.0; if opts.depth { npix } else { 0 }];
    let mut alpha = vec![0.0; if opts.alpha { npix } else { 0 }];
    let mut features = vec![0.0; npix * k];
    let mut pixel_end = vec![0u32; npix];
    let mut pixel_t = vec![1.0; npix];
    let rows = TILE * w;
    let n = grid.tiles_y;
    let outs: Vec<_> = split_chunks(&mut color, rows * 3, n)
        .into_iter()
        .zip(split_chunks(&mut depth, rows, n))
        .zip(split_chunks(&mut alpha, rows, n))
        .zip(split_chunks(&mut features, rows * k, n))
        .zip(split_chunks(&mut pixel_end, rows, n))
        .zip(split_chunks(&mut pixel_t, rows, n))
        .enumerate()
        .collect();
    outs.into_par_iter()
        .for_each(|(ty, (((((col, dep), alp), fea), end), tr))| {
            let mut tile = TileState::new(k);
            for tx in 0..grid.tiles_x {
                let t = ty * grid.tiles_x + tx;
                let list =
                    &bins.pair_gauss[bins.tile_start[t] as usize..bins.tile_start[t + 1] as usize];
                if list.is_empty() {
                    continue;
                }
                let (x0, y0) = (tx * TILE, ty * TILE);
                let (x_end, y_end) = ((x0 + TILE).min(w), (y0 + TILE).min(h));
                tile.reset((x_end - x0) * (y_end - y0));
                // Gaussian-major, front to back: each pixel still sees its Gaussians in depth
                // order, but only the pixels inside a Gaussian's extent are visited.
                for (j, &gi) in list.iter().enumerate() {
                    let s = &splats[gi as usize];
                    let f = &g.features[gi as usize * k..][..k];
                    for y in s.rows(y0, y_end) {
                        for x in s.row_span(y, x0, x_end) {
                            let lp = (y - y0) * TILE + (x - x0);
                            if tile.done[lp] {
                                continue;
                            }
                            let Some(a) = alpha_at(s, x as Real, y as Real, cfg) else {
                                continue;
                            };
                            let trans = tile.trans[lp];
                            let next = trans * (1.0 - a.alpha);
                            if next < cfg.transmittance_min {
                                tile.done[lp] = true;
                                tile.active -= 1;
                                continue;
                            }
                            let wgt = a.alpha * trans;
                            tile.color[lp] += s.color * wgt;
                            tile.depth[lp] += s.depth * wgt;
                            for (o, fv) in tile.feat[lp * k..][..k].iter_mut().zip(f) {
                                *o += wgt * fv;
                            }
                            tile.trans[lp] = next;
                            tile.end[lp] = j as u32 + 1;
                        }
                    }
                    if tile.active == 0 {
                        break;
                    }
                }
                for y in y0..y_end {
                    for x in x0..x_end {
                        let lp = (y - y0) * TILE + (x - x0);
                        let p = (y - y0) * w + x;
                        if !col.is_empty() {
                            col[3 * p..3 * p + 3].copy_from_slice(&tile.color[lp].to_array());
                        }
                        if !dep.is_empty() {
                            dep[p] = tile.depth[lp];
                        }
                        if !alp.is_empty() {
                            alp[p] = 1.0 - tile.trans[lp];
                        }
                        if k > 0 {
                            fea[p * k..][..k].copy_from_slice(&tile.feat[lp * k..][..k]);
                        }
                        end[p] = tile.end[lp];
                        tr[p] = tile.trans[lp];
                    }
                }
            }
        });

    Ok(Rendered {
        width: w,
        height: h,
        num_features: k,
        color,
        depth,
        alpha,
        features,
        radii,
        state: State {
            grid,
            splats,
            rects,
            bins,
            pixel_end,
            pixel_t,
            options: *opts,
        },
    })
}

/// Per-pixel accumulators of one tile, indexed `(y - y0) * TILE + (x - x0)`.
struct TileState {
    trans: [Real; TILE * TILE],
    color: [V3; TILE * TILE],
    depth: [Real; TILE * TILE],
    end: [u32; TILE * TILE],
    done: [bool; TILE * TILE],
    feat: Vec<Real>,
    active: usize,
}

impl TileState {
    fn new(k: usize) -> Self {
        TileState {
            trans: [1.0; TILE * TILE],
            color: [V3::ZERO; TILE * TILE],
            depth: [0.0; TILE * TILE],
            end: [0; TILE * TILE],
            done: [false; TILE * TILE],
            feat: vec![0.0; TILE * TILE * k],
            active: 0,
        }
    }

    fn reset(&mut self, pixels: usize) {
        self.trans.fill(1.0);
        self.color.fill(V3::ZERO);
        self.depth.fill(0.0);
        self.end.fill(0);
        self.done.fill(false);
        self.feat.fill(0.0);
        self.active = pixels;
    }
}
