//! Backward pass: per tile, walk each pixel's list front to back again, turning
//! d(loss)/d(image) into per-(tile, Gaussian) gradients of the screen-space quantities; then,
//! per Gaussian, sum its tiles and run the projection backward.
//!
//! For a pixel value X = sum_i x_i alpha_i T_i, d X / d alpha_i = x_i T_i - R_i / (1 - alpha_i),
//! where R_i = sum_{j > i} x_j alpha_j T_j is what lies behind Gaussian i (the final value
//! minus the running prefix). Walking front to back repeats the forward's exact decisions.

use rayon::prelude::*;

use super::forward::{alpha_at, split_chunks};
use super::math::{dot, V2, V3};
use super::project::{backward_one, geometry, ParamGrads, Pinhole, ScreenGrads};
use super::tiles::rect_area;
use super::{Camera, Gaussians, Gradients, ImageGrads, Rendered, TILE};
use crate::Real;

/// Screen-space gradient slots per (tile, Gaussian) pair ahead of the K feature slots:
/// xy (2), conic (3), opacity, colour (3), depth.
const SLOTS: usize = 10;

fn check_grad(name: &str, grad: Option<&[Real]>, rendered: bool, len: usize) -> Result<(), String> {
    match grad {
        Some(_) if !rendered => Err(format!(
            "a gradient for {name} was given but {name} was not rendered"
        )),
        Some(v) if v.len() != len => Err(format!(
            "the {name} gradient must hold {len} values, got {}",
            v.len()
        )),
        Some(v) if v.iter().any(|x| !x.is_finite()) => {
            Err(format!("the {name} gradient has a non-finite value"))
        }
        _ => Ok(()),
    }
}

/// Buffers of the backward pass, kept between passes: a training loop that allocated them
/// afresh would page-fault (and, with other threads running, shoot down TLBs) over hundreds of
/// megabytes per iteration.
#[derive(Default)]
pub struct BackwardScratch {
    pair_grads: Vec<Real>,
    g_start: Vec<usize>,
    g_pairs: Vec<u32>,
    cursor: Vec<usize>,
}

/// Gradients of a scalar loss with respect to every Gaussian parameter and the camera pose,
/// given d(loss)/d(each rendered image). `g`, `cam` and the options must be the ones `r` was
/// rendered with.
pub fn backward(
    g: &Gaussians,
    cam: &Camera,
    r: &Rendered,
    grads: &ImageGrads,
) -> Result<Gradients, String> {
    let mut out = Gradients::default();
    backward_into(g, cam, r, grads, &mut BackwardScratch::default(), &mut out)?;
    Ok(out)
}

/// [`backward`] into `out` (overwritten), with buffers reused from `scratch`.
pub fn backward_into(
    g: &Gaussians,
    cam: &Camera,
    r: &Rendered,
    grads: &ImageGrads,
    scratch: &mut BackwardScratch,
    out: &mut Gradients,
) -> Result<(), String> {
    let opts = r.state.options;
    let (w, h, k) = (r.width, r.height, r.num_features);
    if cam.intrinsics.width != w || cam.intrinsics.height != h || r.state.splats.len() != g.len() {
        return Err("backward needs the Gaussians and camera the render was made with".into());
    }
    let npix = w * h;
    check_grad("color", grads.color, opts.color, npix * 3)?;
    check_grad("depth", grads.depth, opts.depth, npix)?;
    check_grad("alpha", grads.alpha, opts.alpha, npix)?;
    check_grad("features", grads.features, opts.features && k > 0, npix * k)?;
    let cfg = &opts.config;
    let st = &r.state;
    let bins = &st.bins;
    let stride = SLOTS + k;

    // Per (tile, Gaussian) pair gradients; each tile owns a contiguous range.
    let pair_grads = &mut scratch.pair_grads;
    zeroed(pair_grads, bins.pair_gauss.len() * stride);
    let mut tile_slices = Vec::with_capacity(st.grid.len());
    let mut rest = pair_grads.as_mut_slice();
    for t in 0..st.grid.len() {
        let n = (bins.tile_start[t + 1] - bins.tile_start[t]) as usize;
        let (head, tail) = rest.split_at_mut(n * stride);
        tile_slices.push(head);
        rest = tail;
    }
    tile_slices
        .into_par_iter()
        .enumerate()
        .for_each(|(t, out)| {
            if out.is_empty() {
                return;
            }
            let list =
                &bins.pair_gauss[bins.tile_start[t] as usize..bins.tile_start[t + 1] as usize];
            let (x0, y0) = ((t % st.grid.tiles_x) * TILE, (t / st.grid.tiles_x) * TILE);
            let (x_end, y_end) = ((x0 + TILE).min(w), (y0 + TILE).min(h));
            // Per pixel: the running transmittance and the running sum of gradient x value.
            let mut trans = [1.0 as Real; TILE * TILE];
            let mut prefix = [0.0 as Real; TILE * TILE];
            // Per pixel: sum over channels of gradient x final value.
            let mut total = [0.0 as Real; TILE * TILE];
            for y in y0..y_end {
                for x in x0..x_end {
                    let p = y * w + x;
                    let lp = (y - y0) * TILE + (x - x0);
                    let mut sum = 0.0;
                    if let Some(gc) = grads.color {
                        sum += (0..3)
                            .map(|c| gc[3 * p + c] * r.color[3 * p + c])
                            .sum::<Real>();
                    }
                    if let Some(gd) = grads.depth {
                        sum += gd[p] * r.depth[p];
                    }
                    if let Some(gf) = grads.features {
                        sum += dot(&gf[p * k..][..k], &r.features[p * k..][..k]);
                    }
                    total[lp] = sum;
                }
            }
            // Gaussian-major, front to back, as in the forward pass.
            for (j, &gi) in list.iter().enumerate() {
                let s = &st.splats[gi as usize];
                let f = &g.features[gi as usize * k..][..k];
                let slot = &mut out[j * stride..][..stride];
                for y in s.rows(y0, y_end) {
                    for x in s.row_span(y, x0, x_end) {
                        let p = y * w + x;
                        let lp = (y - y0) * TILE + (x - x0);
                        if j >= st.pixel_end[p] as usize {
                            continue;
                        }
                        let Some(a) = alpha_at(s, x as Real, y as Real, cfg) else {
                            continue;
                        };
                        let t_now = trans[lp];
                        let wgt = a.alpha * t_now;
                        let gc = grads
                            .color
                            .map_or(V3::ZERO, |v| V3::new(v[3 * p], v[3 * p + 1], v[3 * p + 2]));
                        let gd = grads.depth.map_or(0.0, |v| v[p]);
                        let ga = grads.alpha.map_or(0.0, |v| v[p]);
                        let mut x_j = gc.dot(s.color) + gd * s.depth;
                        if let Some(gf) = grads.features {
                            let gf = &gf[p * k..][..k];
                            for (o, gfk) in slot[SLOTS..].iter_mut().zip(gf) {
                                *o += wgt * gfk;
                            }
                            x_j += dot(gf, f);
                        }
                        slot[6] += wgt * gc.x;
                        slot[7] += wgt * gc.y;
                        slot[8] += wgt * gc.z;
                        slot[9] += wgt * gd;
                        prefix[lp] += wgt * x_j;
                        let next = t_now * (1.0 - a.alpha);
                        let behind = total[lp] - prefix[lp] + ga * (next - st.pixel_t[p]);
                        let g_alpha = t_now * (x_j + ga) - behind / (1.0 - a.alpha);
                        if !a.capped {
                            slot[5] += a.falloff * g_alpha;
                            let g_sigma = -a.alpha * g_alpha;
                            let (cv, dx, dy) = (s.conic, a.dx, a.dy);
                            slot[0] -= (cv.x * dx + cv.y * dy) * g_sigma;
                            slot[1] -= (cv.y * dx + cv.z * dy) * g_sigma;
                            slot[2] += 0.5 * dx * dx * g_sigma;
                            slot[3] += dx * dy * g_sigma;
                            slot[4] += 0.5 * dy * dy * g_sigma;
                        }
                        trans[lp] = next;
                    }
                }
            }
        });

    // Each Gaussian's pairs, in tile order, so that its sum is deterministic.
    let n = g.len();
    let BackwardScratch {
        pair_grads,
        g_start,
        g_pairs,
        cursor,
    } = scratch;
    g_start.clear();
    g_start.push(0);
    for i in 0..n {
        g_start.push(g_start[i] + rect_area(&st.rects[i]));
    }
    g_pairs.resize(g_start[n], 0);
    cursor.clear();
    cursor.extend_from_slice(&g_start[..n]);
    for (pair, &i) in bins.pair_gauss.iter().enumerate() {
        g_pairs[cursor[i as usize]] = pair as u32;
        cursor[i as usize] += 1;
    }
    let (pair_grads, g_start, g_pairs) = (&pair_grads[..], &g_start[..], &g_pairs[..]);

    let nc = g.sh_coeffs * 3;
    zeroed(&mut out.means, n * 3);
    zeroed(&mut out.log_scales, n * 3);
    zeroed(&mut out.quats, n * 4);
    zeroed(&mut out.opacity_logits, n);
    zeroed(&mut out.sh, n * nc);
    zeroed(&mut out.features, n * g.num_features);
    zeroed(&mut out.means2d, n * 2);
    out.pose = [0.0; 6];
    const CHUNK: usize = 1024;
    let nch = n.div_ceil(CHUNK);
    let kf = g.num_features;
    let chunks: Vec<_> = split_chunks(&mut out.means, CHUNK * 3, nch)
        .into_iter()
        .zip(split_chunks(&mut out.log_scales, CHUNK * 3, nch))
        .zip(split_chunks(&mut out.quats, CHUNK * 4, nch))
        .zip(split_chunks(&mut out.opacity_logits, CHUNK, nch))
        .zip(split_chunks(&mut out.sh, CHUNK * nc, nch))
        .zip(split_chunks(&mut out.features, CHUNK * kf, nch))
        .zip(split_chunks(&mut out.means2d, CHUNK * 2, nch))
        .enumerate()
        .collect();
    let pin = Pinhole::new(cam, cfg);
    let pose_parts: Vec<[Real; 6]> = chunks
        .into_par_iter()
        .map(|(c, ((((((gm, gs), gq), go), gsh), gfeat), gm2))| {
            let mut pose = [0.0; 6];
            for li in 0..gm.len() / 3 {
                let i = c * CHUNK + li;
                let pairs = &g_pairs[g_start[i]..g_start[i + 1]];
                if pairs.is_empty() {
                    continue;
                }
                let mut sg = ScreenGrads::default();
                for &pr in pairs {
                    let s = &pair_grads[pr as usize * stride..][..stride];
                    sg.xy += V2::new(s[0], s[1]);
                    sg.conic += V3::new(s[2], s[3], s[4]);
                    sg.opacity += s[5];
                    sg.color += V3::new(s[6], s[7], s[8]);
                    sg.depth += s[9];
                    if k > 0 {
                        for (o, v) in gfeat[li * kf..][..kf].iter_mut().zip(&s[SLOTS..]) {
                            *o += v;
                        }
                    }
                }
                gm2[2 * li] = sg.xy.x;
                gm2[2 * li + 1] = sg.xy.y;
                let Some(geo) = geometry(g, i, cam, &pin, cfg) else {
                    continue;
                };
                let part = backward_one(
                    g,
                    i,
                    cam,
                    &pin,
                    &geo,
                    opts.sh_degree,
                    opts.color,
                    &sg,
                    ParamGrads {
                        mean: &mut gm[3 * li..3 * li + 3],
                        log_scale: &mut gs[3 * li..3 * li + 3],
                        quat: &mut gq[4 * li..4 * li + 4],
                        opacity_logit: &mut go[li],
                        sh: &mut gsh[nc * li..nc * (li + 1)],
                    },
                );
                for (p, v) in pose.iter_mut().zip(part) {
                    *p += v;
                }
            }
            pose
        })
        .collect();
    for part in pose_parts {
        for (p, v) in out.pose.iter_mut().zip(part) {
            *p += v;
        }
    }
    Ok(())
}

/// Makes `v` hold `len` zeros, reusing its allocation.
fn zeroed(v: &mut Vec<Real>, len: usize) {
    v.truncate(len);
    v.par_chunks_mut(1 << 16).for_each(|c| c.fill(0.0));
    v.resize(len, 0.0);
}
