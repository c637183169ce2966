//! Backward pass: per tile, walk each pixel's list front to back again, turning
//! d(loss)/d(image) into per-(tile, Gaussian) gradients of the screen-space quantities; then,
//! per Gaussian, sum its tiles and run the projection backward (eight Gaussians at a time,
//! [`super::project_backward`]).
//!
//! For a pixel value X = sum_i x_i alpha_i T_i, d X / d alpha_i = x_i T_i - R_i / (1 - alpha_i),
//! where R_i = sum_{j > i} x_j alpha_j T_j is what lies behind Gaussian i (the final value
//! minus the running prefix). Walking front to back repeats the forward's exact decisions.

use rayon::prelude::*;

use super::composite::{
    cover_kept, for_each_group, prefetch_gaussian, TileRect, PREFETCH, TILE_LANES,
};
use super::forward::{split_chunks, Layer};
use super::lanes::{dispatch, Lanes, Simd, LANES};
use super::math::{V2, V3};
use super::project::View;
use super::project_backward::{backward_task, conic_to_cov_grad, BlockGrads, ScreenGrads};
use super::tiles::rect_area;
use super::{Camera, Gaussians, Gradients, ImageGrads, RasterConfig, Rendered, TILE};
use crate::optim::rows_in;
use crate::prefetch::{prefetch, prefetch_l2};
use crate::Real;

/// The screen-space gradient slots of a (tile, Gaussian) pair, ahead of its K feature slots.
mod slot {
    pub const X: usize = 0;
    pub const Y: usize = 1;
    /// The conic entries a, b, c.
    pub const CONIC: usize = 2;
    pub const OPACITY: usize = 5;
    /// Red, green, blue.
    pub const COLOR: usize = 6;
    pub const DEPTH: usize = 9;
    /// Sum of blending weights alpha * T (not a gradient: how much of the image it makes).
    pub const WEIGHT: usize = 10;
    pub const COUNT: usize = 11;
}
const SLOTS: usize = slot::COUNT;

/// How many Gaussians ahead the per-Gaussian sums prefetch their pairs' gradients.
const PAIR_PREFETCH: usize = 4;

/// How many groups ahead the backward walk prefetches the kept falloffs.
const FALLOFF_PREFETCH: usize = 16;
/// Values in a cache line.
const LINE_VALUES: usize = 64 / std::mem::size_of::<Real>();

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
    main: LayerScratch,
    coarse: LayerScratch,
}

/// One layer's per-pair gradients, and each Gaussian's pairs.
#[derive(Default)]
struct LayerScratch {
    pair_grads: Vec<Real>,
    /// Gaussian i's pairs are `g_pairs[g_start[i]..g_start[i + 1]]`, in tile order.
    g_start: Vec<usize>,
    g_pairs: Vec<u32>,
    cursor: Vec<usize>,
}

impl LayerScratch {
    /// Gaussian `i`'s pairs.
    fn pairs(&self, i: usize) -> &[u32] {
        &self.g_pairs[self.g_start[i]..self.g_start[i + 1]]
    }
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

/// [`backward`] into `out`, with buffers reused from `scratch`: the rows of the Gaussians on
/// screen (`out.rows`) and the pose gradient are overwritten, the other rows keep what the last
/// call left there (zeros where `out` is new or the map grew).
pub fn backward_into(
    g: &Gaussians,
    cam: &Camera,
    r: &Rendered,
    grads: &ImageGrads,
    scratch: &mut BackwardScratch,
    out: &mut Gradients,
) -> Result<(), String> {
    let st = &r.state;
    let opts = st.options;
    let (w, h, k) = (r.width, r.height, r.num_features);
    if cam.intrinsics.width != w || cam.intrinsics.height != h || st.main.splats.len() != g.len() {
        return Err("backward needs the Gaussians and camera the render was made with".into());
    }
    let npix = w * h;
    check_grad("color", grads.color, opts.color, npix * 3)?;
    check_grad("depth", grads.depth, opts.depth, npix)?;
    check_grad("alpha", grads.alpha, opts.alpha, npix)?;
    let feature_len = r.feature_width * r.feature_height * k;
    check_grad(
        "features",
        grads.features,
        opts.features && k > 0,
        feature_len,
    )?;
    let cfg = &opts.config;
    let coarse = !st.coarse.splats.is_empty();

    // The main layer, and the features' own beside it.
    let main = TileJob {
        layer: &st.main,
        features: g.features,
        rendered: [&r.color, &r.depth, if coarse { &[] } else { &r.features }],
        grads: ImageGrads {
            features: if coarse { None } else { grads.features },
            ..*grads
        },
        k: if coarse { 0 } else { k },
        colour: true,
        cfg,
        kept_falloffs: opts.for_backward,
    };
    if coarse {
        let cfg = &cfg.for_features();
        let features = TileJob {
            layer: &st.coarse,
            features: g.features,
            rendered: [&[], &[], &r.features],
            grads: ImageGrads {
                features: grads.features,
                ..Default::default()
            },
            k,
            colour: false,
            cfg,
            kept_falloffs: opts.for_backward,
        };
        // Side by side, as the forward pass composites them.
        rayon::join(
            || walk_layer(opts.simd, &main, &mut scratch.main),
            || walk_layer(opts.simd, &features, &mut scratch.coarse),
        );
    } else {
        walk_layer(opts.simd, &main, &mut scratch.main);
    }
    let scale = opts.feature_scale as Real;
    let strides = [SLOTS + main.k, SLOTS + k];
    let layers = [&st.main, &st.coarse];
    let layer_scratch = [&scratch.main, &scratch.coarse];
    // The layers this pass walked: the main one, and the features' own when coarser.
    let layers_walked = 1 + usize::from(coarse);

    // Only the rows of Gaussians on screen are written (every value of each); the others keep
    // what they held, stale (zeros in new arrays): no pass reads them (see `Gradients::rows`),
    // and clearing them cost 4-6% of the mapper bench's backward.
    let n = g.len();
    let nc = g.sh_coeffs * 3;
    let kf = g.num_features;
    let widths = [3, 3, 4, 1, nc, kf, 2, 1];
    for (v, w) in out.arrays_mut().into_iter().zip(widths) {
        v.resize(n * w, 0.0);
    }
    let on_screen = |i: usize| {
        layers
            .iter()
            .any(|l| l.rects.get(i).is_some_and(|r| rect_area(r) > 0))
    };
    let rows: Vec<u32> = (0..n as u32).filter(|&i| on_screen(i as usize)).collect();
    out.pose = [0.0; 6];
    const CHUNK: usize = 1024;
    let nch = n.div_ceil(CHUNK);
    let chunks: Vec<_> = split_chunks(&mut out.means, CHUNK * 3, nch)
        .into_iter()
        .zip(split_chunks(&mut out.log_scales, CHUNK * 3, nch))
        .zip(split_chunks(&mut out.quats, CHUNK * 4, nch))
        .zip(split_chunks(&mut out.opacity_logits, CHUNK, nch))
        .zip(split_chunks(&mut out.sh, CHUNK * nc, nch))
        .zip(split_chunks(&mut out.features, CHUNK * kf, nch))
        .zip(split_chunks(&mut out.means2d, CHUNK * 2, nch))
        .zip(split_chunks(&mut out.contribution, CHUNK, nch))
        .enumerate()
        .collect();
    let view = View::new(g, cam, &opts);
    // The slots of Gaussian `i`'s pairs in layer `l` that added to a pixel (the walk wrote no
    // others), in tile order.
    let added_slots = |l: usize, i: usize| {
        let (ls, stride) = (layer_scratch[l], strides[l]);
        ls.pairs(i)
            .iter()
            .filter(move |&&pr| layers[l].added[pr as usize])
            .map(move |&pr| &ls.pair_grads[pr as usize * stride..][..stride])
    };
    let pose_parts: Vec<[Real; 6]> = chunks
        .into_par_iter()
        .map(|(c, (((((((gm, gs), gq), go), gsh), gfeat), gm2), gw))| {
            let first = c * CHUNK;
            let len = gw.len();
            // The chunk's screen-space gradients, and which of its Gaussians are on screen.
            let mut screen = vec![ScreenGrads::default(); len];
            let mut on = vec![false; len];
            let mine = rows_in(&rows, first, CHUNK);
            for (at, &i) in mine.iter().enumerate() {
                // A Gaussian's pairs lie anywhere in the per-pair buffers (in tile order).
                if let Some(&ahead) = mine.get(at + PAIR_PREFETCH) {
                    for l in 0..layers_walked {
                        added_slots(l, ahead as usize).for_each(prefetch_l2);
                    }
                }
                let (i, li) = (i as usize, i as usize - first);
                let feat_row = &mut gfeat[li * kf..][..kf];
                feat_row.fill(0.0);
                // Each layer's pairs, in tile order, so that the sums are deterministic.
                let (mut sg, weight) = sum_slots(added_slots(0, i), feat_row);
                let low = if coarse {
                    sum_slots(added_slots(1, i), feat_row).0
                } else {
                    ScreenGrads::default()
                };
                // Densification reads the main layer's screen-space gradient alone.
                gm2[2 * li] = sg.xy.x;
                gm2[2 * li + 1] = sg.xy.y;
                gw[li] = weight;
                if coarse {
                    // The coarse splat's centre is (xy - origin) / s and its covariance
                    // (cov2d - dilation) / s^2 + dilation or cov2d / s^2 (see `project`).
                    sg.xy += low.xy / scale;
                    sg.opacity += low.opacity;
                    let gc = conic_to_cov_grad(st.coarse.splats[i].conic, low.conic);
                    let s2 = scale * scale;
                    sg.cov += V3::new(gc[0][0], gc[0][1], gc[1][1]) / s2;
                }
                screen[li] = sg;
                on[li] = true;
            }
            let out = BlockGrads {
                mean: gm,
                log_scale: gs,
                quat: gq,
                opacity_logit: go,
                sh: gsh,
            };
            backward_task(opts.simd, &view, first, &screen, &on, out)
        })
        .collect();
    for part in pose_parts {
        for (p, v) in out.pose.iter_mut().zip(part) {
            *p += v;
        }
    }
    out.rows = rows;
    Ok(())
}

/// The sums of a Gaussian's pair `slots` in one layer: the screen-space gradients and the
/// blending weights, returned (in registers: summed into an array in memory, each Gaussian's
/// sums were stored piecewise and loaded whole, a stall), and the features' gradients added
/// to `feat_row`.
#[inline(always)]
fn sum_slots<'a>(
    slots: impl Iterator<Item = &'a [Real]>,
    feat_row: &mut [Real],
) -> (ScreenGrads, Real) {
    let (mut sg, mut weight) = (ScreenGrads::default(), 0.0);
    for s in slots {
        let v3 = |i: usize| V3::new(s[i], s[i + 1], s[i + 2]);
        sg.xy += V2::new(s[slot::X], s[slot::Y]);
        sg.conic += v3(slot::CONIC);
        sg.opacity += s[slot::OPACITY];
        sg.color += v3(slot::COLOR);
        sg.depth += s[slot::DEPTH];
        weight += s[slot::WEIGHT];
        for (o, v) in feat_row.iter_mut().zip(&s[SLOTS..]) {
            *o += v;
        }
    }
    (sg, weight)
}

/// Walks every tile of `job`'s layer into per-pair gradients (each tile owns a contiguous
/// range of `ls.pair_grads` and writes the slots of the pairs that added to a pixel), and
/// meanwhile lists each Gaussian's pairs.
fn walk_layer(simd: Simd, job: &TileJob, ls: &mut LayerScratch) {
    let layer = job.layer;
    let bins = &layer.bins;
    let stride = SLOTS + job.k;
    let LayerScratch {
        pair_grads,
        g_start,
        g_pairs,
        cursor,
    } = ls;
    pair_grads.resize(bins.pair_gauss.len() * stride, 0.0);
    let mut tile_slices = Vec::with_capacity(layer.grid.len());
    let mut rest = pair_grads.as_mut_slice();
    for t in 0..layer.grid.len() {
        let (head, tail) = rest.split_at_mut(bins.list(t).len() * stride);
        tile_slices.push(head);
        rest = tail;
    }
    let walk = || {
        tile_slices.into_par_iter().enumerate().for_each_init(
            || Box::new(TileGrads::default()),
            |tg, (t, slots)| {
                if !slots.is_empty() {
                    tile_backward(simd, job, t, tg, slots);
                }
            },
        )
    };
    // The listing reads only the binning, so one thread makes it while the other walks tiles
    // (serial after the walk, it left a thread idle: 2-2.6 ms an iteration of the mapper bench).
    let list = || {
        let n = layer.rects.len();
        g_start.clear();
        g_start.push(0);
        for i in 0..n {
            g_start.push(g_start[i] + rect_area(&layer.rects[i]));
        }
        g_pairs.resize(g_start[n], 0);
        cursor.clear();
        cursor.extend_from_slice(&g_start[..n]);
        for (pair, &i) in bins.pair_gauss.iter().enumerate() {
            g_pairs[cursor[i as usize]] = pair as u32;
            cursor[i as usize] += 1;
        }
    };
    rayon::join(walk, list);
}

/// What every tile of one layer's backward walk reads.
struct TileJob<'a> {
    layer: &'a Layer,
    /// The Gaussians' features, [N, K].
    features: &'a [Real],
    /// The layer's rendered colour, depth and features (empty where it has none).
    rendered: [&'a [Real]; 3],
    grads: ImageGrads<'a>,
    /// Feature channels the layer composited.
    k: usize,
    /// Whether the layer composited colour and depth (the main layer does).
    colour: bool,
    cfg: &'a RasterConfig,
    /// Whether the forward pass kept the layer's falloffs.
    kept_falloffs: bool,
}

/// One tile's image gradients and forward results, per pixel, structure of arrays (indexed like
/// the forward pass's accumulators), and the running state of the backward walk.
struct TileGrads {
    color: [[Real; TILE_LANES]; 3],
    depth: [Real; TILE_LANES],
    alpha: [Real; TILE_LANES],
    /// Sum over channels of gradient x final value.
    total: [Real; TILE_LANES],
    /// Final transmittance, and how many Gaussians of the list the pixel composited.
    t_final: [Real; TILE_LANES],
    end: [u32; TILE_LANES],
    /// Transmittance before the current Gaussian, and the running sum of gradient x value.
    trans: [Real; TILE_LANES],
    prefix: [Real; TILE_LANES],
}

impl Default for TileGrads {
    fn default() -> Self {
        TileGrads {
            color: [[0.0; TILE_LANES]; 3],
            depth: [0.0; TILE_LANES],
            alpha: [0.0; TILE_LANES],
            total: [0.0; TILE_LANES],
            t_final: [0.0; TILE_LANES],
            end: [0; TILE_LANES],
            trans: [0.0; TILE_LANES],
            prefix: [0.0; TILE_LANES],
        }
    }
}

impl TileGrads {
    /// Gathers tile `r`'s pixels (pixels outside the image composite nothing).
    #[inline(always)]
    fn load<L: Lanes>(&mut self, job: &TileJob, r: &TileRect) {
        let (w, k, st, ig) = (job.layer.width, job.k, job.layer, job.grads);
        let [color, depth, features] = job.rendered;
        self.end.fill(0);
        self.trans.fill(1.0);
        self.prefix.fill(0.0);
        for y in r.y0..r.y_end {
            for x in r.x0..r.x_end {
                let (p, lp) = (y * w + x, (y - r.y0) * TILE + (x - r.x0));
                let mut total = 0.0;
                for c in 0..3 {
                    let g = ig.color.map_or(0.0, |v| v[3 * p + c]);
                    self.color[c][lp] = g;
                    total += g * color.get(3 * p + c).copied().unwrap_or(0.0);
                }
                let gd = ig.depth.map_or(0.0, |v| v[p]);
                self.depth[lp] = gd;
                total += gd * depth.get(p).copied().unwrap_or(0.0);
                if let Some(gf) = ig.features {
                    total += L::dot(&gf[p * k..][..k], &features[p * k..][..k]);
                }
                self.total[lp] = total;
                self.alpha[lp] = ig.alpha.map_or(0.0, |v| v[p]);
                self.t_final[lp] = st.pixel_t[p];
                self.end[lp] = st.pixel_end[p];
            }
        }
    }
}

/// The backward walk over tile `t` through the implementation `simd` chose: `slots` receives
/// one gradient slot per pair of the tile's list.
fn tile_backward(simd: Simd, job: &TileJob, t: usize, tg: &mut TileGrads, slots: &mut [Real]) {
    dispatch!(
        simd,
        walk_tile(
            job: &TileJob,
            t: usize,
            tg: &mut TileGrads,
            slots: &mut [Real],
        )
    )
}

/// [`walk`] compiled for what the layer's loss has: the features' own layer has no colour or
/// depth, and a training loss no alpha term, whose gradients would be zeros walked through
/// every group (the same values either way).
#[inline(always)]
fn walk_tile<L: Lanes>(job: &TileJob, t: usize, tg: &mut TileGrads, slots: &mut [Real]) {
    match (job.colour, job.grads.alpha.is_some()) {
        (true, true) => walk::<L, true, true>(job, t, tg, slots),
        (true, false) => walk::<L, true, false>(job, t, tg, slots),
        // The features' own layer: alpha is rendered in the main one.
        (false, _) => walk::<L, false, false>(job, t, tg, slots),
    }
}

/// Walks tile `t`'s list front to back as the forward pass did (Gaussian-major, eight pixels
/// at a time), turning d(loss)/d(pixel) into each pair's screen-space and feature gradients;
/// `COLOUR`: the layer composites colour and depth, `ALPHA`: the loss has an alpha term.
#[inline(always)]
fn walk<L: Lanes, const COLOUR: bool, const ALPHA: bool>(
    job: &TileJob,
    t: usize,
    tg: &mut TileGrads,
    slots: &mut [Real],
) {
    let (st, k, cfg) = (job.layer, job.k, job.cfg);
    let stride = SLOTS + k;
    let r = TileRect::new(&st.grid, t, st.width, st.height);
    let cols = r.columns();
    tg.load::<L>(job, &r);
    let list = st.bins.list(t);
    // Past the last pixel's last contributor nothing has a gradient.
    let walked = tg.end.iter().copied().max().unwrap_or(0) as usize;
    let added = &st.added[st.bins.tile_start[t] as usize..][..walked];
    let (zero, one, half) = (L::splat(0.0), L::splat(1.0), L::splat(0.5));
    let gf = job.grads.features.filter(|_| k > 0);
    // The forward pass's falloffs, when it kept them: a group at a time, in the same order.
    let kept = job
        .kept_falloffs
        .then(|| &st.falloffs[t / st.grid.tiles_x][st.falloff_start[t]..]);
    let mut group = 0;
    // The walk reaches only the pairs that added, so it prefetches only theirs (a third of
    // the features' layer's pairs add nothing).
    let mut upcoming = list[..walked]
        .iter()
        .zip(added)
        .filter_map(|(&gi, &a)| a.then_some(gi));
    let mut prefetch_next = || {
        if let Some(gi) = upcoming.next() {
            prefetch_gaussian(gi, &st.splats, job.features, k);
        }
    };
    (0..PREFETCH).for_each(|_| prefetch_next());
    for (j, &gi) in list[..walked].iter().enumerate() {
        // Only the pairs that added to a pixel have a gradient (the per-Gaussian sums skip
        // the others' slots, left unwritten).
        if !added[j] {
            continue;
        }
        prefetch_next();
        if let Some(kept) = kept {
            // The kept falloffs are read in order, but from L3 or memory: two lines ~8 pairs on.
            let at = (group + FALLOFF_PREFETCH) * LANES;
            if let Some(ahead) = kept.get(at..=at + LINE_VALUES) {
                prefetch(ahead);
            }
        }
        let s = &st.splats[gi as usize];
        let f = &job.features[gi as usize * k..][..k];
        let (slot, feat_slot) = slots[j * stride..][..stride].split_at_mut(SLOTS);
        // The first lane to reach the features' slot writes it rather than adds to it: no
        // zeroing pass (a call to memset per pair).
        let mut fresh = true;
        let color = [
            L::splat(s.color.x),
            L::splat(s.color.y),
            L::splat(s.color.z),
        ];
        let depth = L::splat(s.depth);
        let (a, b, c) = (s.conic.x, s.conic.y, s.conic.z);
        let mut acc = [zero; SLOTS];
        for_each_group(s, &r, |grp| {
            let lp = grp.lp;
            // The pixels whose list reaches this Gaussian.
            let open = L::below(j as u32, &tg.end[lp..]);
            let cv = match kept {
                Some(kept) => {
                    let falloff = L::load(&kept[group * LANES..]);
                    group += 1;
                    cover_kept(s, L::load(&cols[grp.gx..]), falloff, open, cfg)
                }
                None => grp.cover::<L>(s, &cols, open, cfg),
            };
            let ok = cv.ok;
            if L::bits(ok) == 0 {
                return;
            }
            let t = L::load(&tg.trans[lp..]);
            let wgt = L::select(ok, cv.alpha.mul(t), zero);
            // Spelt out, as the splats above: `array::map` was not inlined into the AVX2 walk,
            // so these loads went through a call compiled without AVX2 that passes vectors in
            // memory (2% of the mapper bench's profile; the backward 3-6% faster without it).
            let mut x_j = zero;
            if COLOUR {
                let gc = [
                    L::load(&tg.color[0][lp..]),
                    L::load(&tg.color[1][lp..]),
                    L::load(&tg.color[2][lp..]),
                ];
                let gd = L::load(&tg.depth[lp..]);
                x_j = gc[0]
                    .mul(color[0])
                    .add(gc[1].mul(color[1]))
                    .add(gc[2].mul(color[2]))
                    .add(gd.mul(depth));
                for ch in 0..3 {
                    acc[slot::COLOR + ch] = acc[slot::COLOR + ch].add(wgt.mul(gc[ch]));
                }
                acc[slot::DEPTH] = acc[slot::DEPTH].add(wgt.mul(gd));
                acc[slot::WEIGHT] = acc[slot::WEIGHT].add(wgt);
            }
            if let Some(gf) = gf {
                let mut w = [0.0; LANES];
                wgt.store(&mut w);
                // Each lane's dot product as partial sums, reduced together: eight scalar
                // reductions stored and loaded back as a vector stalled the walk.
                let (mut parts, mut tails) = ([zero; LANES], [0.0; LANES]);
                let mut bits = L::bits(ok);
                let p0 = grp.y * st.width + r.x0 + grp.gx;
                while bits != 0 {
                    let l = bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    let g = &gf[(p0 + l) * k..][..k];
                    (parts[l], tails[l]) = if fresh {
                        fresh = false;
                        L::axpy_dot::<true>(feat_slot, w[l], g, f)
                    } else {
                        L::axpy_dot::<false>(feat_slot, w[l], g, f)
                    };
                }
                let mut dots = L::load(&L::hsum8(parts));
                // Scalar tails, stored and loaded as a vector, stall: only where there are any.
                if k % LANES != 0 {
                    dots = dots.add(L::load(&tails));
                }
                x_j = x_j.add(dots);
            }
            let prefix = L::load(&tg.prefix[lp..]);
            let prefix_next = prefix.add(wgt.mul(x_j));
            let next = t.mul(one.sub(cv.alpha));
            let total = L::load(&tg.total[lp..]);
            // What lies behind this Gaussian, and d(loss)/d(its alpha).
            let mut behind = total.sub(prefix_next);
            let mut x_a = x_j;
            if ALPHA {
                let ga = L::load(&tg.alpha[lp..]);
                let t_final = L::load(&tg.t_final[lp..]);
                behind = behind.add(ga.mul(next.sub(t_final)));
                x_a = x_j.add(ga);
            }
            let g_alpha = t.mul(x_a).sub(behind.div(one.sub(cv.alpha)));
            let g_alpha = L::select(L::and_not(ok, cv.capped), g_alpha, zero);
            acc[slot::OPACITY] = acc[slot::OPACITY].add(cv.falloff.mul(g_alpha));
            let g_sigma = zero.sub(cv.alpha.mul(g_alpha));
            let dx = cv.dx;
            let dy = grp.y as Real - s.xy.y;
            let d_mean = [
                L::splat(a).mul(dx).add(L::splat(b * dy)),
                L::splat(b).mul(dx).add(L::splat(c * dy)),
            ];
            for (i, d) in d_mean.into_iter().enumerate() {
                acc[slot::X + i] = acc[slot::X + i].sub(d.mul(g_sigma));
            }
            let d_conic = [
                half.mul(dx).mul(dx),
                dx.mul(L::splat(dy)),
                L::splat(0.5 * dy * dy),
            ];
            for (i, d) in d_conic.into_iter().enumerate() {
                acc[slot::CONIC + i] = acc[slot::CONIC + i].add(d.mul(g_sigma));
            }
            next.store_where(ok, t, &mut tg.trans[lp..]);
            prefix_next.store_where(ok, prefix, &mut tg.prefix[lp..]);
        });
        // A pair without a features' gradient (none was given) has zeros there.
        if fresh && k > 0 {
            feat_slot.fill(0.0);
        }
        // Eight of the pair's sums in one transposition, then the rest.
        let (first, rest) = acc.split_at(8);
        slot[..8].copy_from_slice(&L::hsum8(first.try_into().unwrap()));
        for (o, v) in slot[8..].iter_mut().zip(rest) {
            *o = v.hsum();
        }
    }
}
