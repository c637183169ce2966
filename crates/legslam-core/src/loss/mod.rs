//! Image losses of the mapper, each returning its value and writing d(loss)/d(rendered image)
//! into a caller-provided buffer (the image-sized buffers are the reusable [`Ssim`] / [`Loss`]
//! workspaces; SSIM takes a row's scratch at a time):
//!
//! L = w_color ((1 - lambda) L1(color) + lambda (1 - SSIM(color)))
//!   + w_depth L1 over valid depth + w_feat mean(1 - cos(feature, target feature)).
//!
//! Images are row-major, channel-last `&[Real]`. Values are summed over fixed runs of pixels
//! (rows, or up to 256 pixels; some terms in `Real` lanes within a run), then in f64 over fixed
//! blocks of runs, in a fixed order, so results do not depend on the thread count.

// Real -> f64 via f64::from is lossless, and a no-op under the `f64` feature.
#![allow(clippy::useless_conversion)]

mod cosine;
mod l1;
mod ssim;

pub use cosine::{cosine, COS_EPS};
pub use l1::{depth_l1, l1};
pub use ssim::Ssim;

use rayon::prelude::*;

use crate::Real;

/// Weights of the mapper's loss terms.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LossWeights {
    /// Weight of the whole colour term.
    pub color: Real,
    /// Share of `1 - SSIM` in the colour term (the rest is L1), 0.2 as in 3DGS.
    pub ssim_lambda: Real,
    pub depth: Real,
    pub feature: Real,
}

impl Default for LossWeights {
    fn default() -> Self {
        LossWeights {
            color: 1.0,
            ssim_lambda: 0.2,
            depth: 1.0,
            feature: 1.0,
        }
    }
}

/// Rendered depth and its target (0 or non-finite target = invalid), one value per pixel.
#[derive(Clone, Copy, Debug)]
pub struct DepthInputs<'a> {
    pub rendered: &'a [Real],
    pub target: &'a [Real],
}

/// Rendered feature map and its target, `channels` values per pixel at their own resolution.
#[derive(Clone, Copy, Debug)]
pub struct FeatureInputs<'a> {
    pub rendered: &'a [Real],
    pub target: FeatureTarget<'a>,
    pub channels: usize,
    /// Pixels with a valid target; `None` uses every pixel.
    pub mask: Option<&'a [bool]>,
}

/// The target of the feature loss.
#[derive(Clone, Copy, Debug)]
pub enum FeatureTarget<'a> {
    /// One vector per pixel, like the rendered map.
    Pixels(&'a [Real]),
    /// Rows of vectors as wide as the image, of which every pixel row blends two: row y's
    /// targets are `rows[b.lower] + b.weight (rows[b.upper] - rows[b.lower])` for
    /// `b = blends[y]`. A target upsampled bilinearly from a coarse grid is this once the
    /// grid's rows are upsampled along x; the loss then reads a few rows instead of an image
    /// of targets (64 channels at 160x120 are 4.9 MB to write and read back).
    Blended {
        rows: &'a [Real],
        blends: &'a [Blend],
    },
}

/// Which two rows of a [`FeatureTarget::Blended`] a pixel row blends, and how.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Blend {
    pub lower: usize,
    pub upper: usize,
    /// The upper row's share, in [0, 1].
    pub weight: Real,
}

/// What the combined loss compares. Colour is RGB at `width x height`, as is depth.
#[derive(Clone, Copy, Debug)]
pub struct LossInputs<'a> {
    pub width: usize,
    pub height: usize,
    pub color: &'a [Real],
    pub target_color: &'a [Real],
    /// Pixels the colour L1 counts; `None` counts all. SSIM always uses the whole image.
    pub color_mask: Option<&'a [bool]>,
    pub depth: Option<DepthInputs<'a>>,
    pub features: Option<FeatureInputs<'a>>,
}

/// Where the combined loss writes its gradients (overwritten, not accumulated). A buffer must
/// be given exactly when its input is.
#[derive(Debug)]
pub struct LossGrads<'a> {
    pub color: &'a mut [Real],
    pub depth: Option<&'a mut [Real]>,
    pub features: Option<&'a mut [Real]>,
}

/// The unweighted value of every term (0 for an absent one) and the weighted total.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LossTerms {
    pub total: f64,
    pub color_l1: f64,
    /// SSIM itself (the loss uses 1 - SSIM).
    pub ssim: f64,
    pub depth_l1: f64,
    /// Mean 1 - cos over the counted pixels.
    pub feature: f64,
}

/// The mapper's combined loss with its reusable SSIM workspace.
#[derive(Debug, Default)]
pub struct Loss {
    pub weights: LossWeights,
    ssim: Ssim,
}

impl Loss {
    pub fn new(weights: LossWeights) -> Self {
        Loss {
            weights,
            ssim: Ssim::new(),
        }
    }

    /// Evaluates every term and writes d(total)/d(rendered colour, depth, features).
    pub fn evaluate(&mut self, inputs: &LossInputs, grads: LossGrads) -> Result<LossTerms, String> {
        let w = self.weights;
        let (width, height) = (inputs.width, inputs.height);
        let l1_scale = w.color * (1.0 - w.ssim_lambda);
        let ssim_scale = w.color * w.ssim_lambda;
        check_len("rendered colour", inputs.color.len(), width * height * 3)?;
        let ssim = &mut self.ssim;
        let LossGrads {
            color: grad_color,
            depth: grad_depth,
            features: grad_features,
        } = grads;
        let colour = || -> Result<(f64, f64), String> {
            let l1 = l1::l1_into(
                inputs.color,
                inputs.target_color,
                inputs.color_mask,
                3,
                grad_color,
                Emit::set(l1_scale),
            )?;
            // d(1 - SSIM) = -dSSIM, added onto the L1 gradient.
            let ssim_grad = (ssim_scale != 0.0).then_some((grad_color, Emit::add(-ssim_scale)));
            let s = ssim.run(
                inputs.color,
                inputs.target_color,
                (width, height, 3),
                ssim_grad,
            )?;
            Ok((l1, s))
        };
        let depth = || match (inputs.depth, grad_depth) {
            (Some(d), Some(g)) => {
                check_len("rendered depth", d.rendered.len(), width * height)?;
                l1::depth_l1_into(d.rendered, d.target, g, Emit::set(w.depth))
            }
            (None, None) => Ok(0.0),
            _ => Err("depth needs both its inputs and a gradient buffer, or neither".into()),
        };
        let feature = || match (inputs.features, grad_features) {
            (Some(f), Some(g)) => cosine::cosine_into(
                f.rendered,
                f.target,
                f.channels,
                f.mask,
                g,
                Emit::set(w.feature),
            ),
            (None, None) => Ok(0.0),
            _ => Err("features need both their inputs and a gradient buffer, or neither".into()),
        };
        // The colour terms beside depth and features: each term is parallel within, and one
        // after another each ended with a thread waiting for the other.
        let (colour, (depth, feature)) = rayon::join(colour, || rayon::join(depth, feature));
        let (color_l1, ssim) = colour?;
        let mut t = LossTerms {
            color_l1,
            ssim,
            depth_l1: depth?,
            feature: feature?,
            ..LossTerms::default()
        };
        t.total = f64::from(l1_scale) * t.color_l1
            + f64::from(ssim_scale) * (1.0 - t.ssim)
            + f64::from(w.depth) * t.depth_l1
            + f64::from(w.feature) * t.feature;
        Ok(t)
    }
}

/// How a term writes `scale * d(term)/d(input)` into a gradient buffer: set or add.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Emit {
    pub scale: Real,
    pub add: bool,
}

impl Emit {
    pub fn set(scale: Real) -> Self {
        Emit { scale, add: false }
    }
    pub fn add(scale: Real) -> Self {
        Emit { scale, add: true }
    }
    #[inline]
    pub fn put(self, g: &mut Real, d: Real) {
        *g = if self.add {
            *g + self.scale * d
        } else {
            self.scale * d
        };
    }
}

/// Checks a per-pixel term's buffers (`what` names the term in errors; a target of
/// `target_len` values, or `None` for one checked by the term) and returns how many pixels the
/// mask counts (all without a mask).
pub(crate) fn pixel_counts(
    what: &str,
    rendered: &[Real],
    target_len: Option<usize>,
    grad: &[Real],
    mask: Option<&[bool]>,
    channels: usize,
) -> Result<usize, String> {
    if channels == 0 || rendered.len() % channels != 0 {
        return Err(format!(
            "{what}: the rendered image holds {} values, not a whole number of {channels}-channel pixels",
            rendered.len()
        ));
    }
    let pixels = rendered.len() / channels;
    if let Some(len) = target_len {
        check_len(&format!("{what} target"), len, rendered.len())?;
    }
    check_len(
        &format!("{what} gradient buffer"),
        grad.len(),
        rendered.len(),
    )?;
    let counted = match mask {
        Some(m) => {
            check_len(&format!("{what} mask (one per pixel)"), m.len(), pixels)?;
            m.iter().filter(|&&b| b).count()
        }
        None => pixels,
    };
    Ok(counted)
}

pub(crate) fn check_len(name: &str, got: usize, want: usize) -> Result<(), String> {
    if got == want {
        Ok(())
    } else {
        Err(format!("the {name} must hold {want} values, got {got}"))
    }
}

/// Fixed number of partial sums, so the reduction order never depends on the thread count.
const BLOCKS: usize = 64;

/// Runs `f(item index, item)` over the `item`-value items of `buf` in parallel and returns
/// the sum of its results, added in a fixed order.
pub(crate) fn sum_items(
    buf: &mut [Real],
    item: usize,
    f: impl Fn(usize, &mut [Real]) -> f64 + Sync,
) -> f64 {
    if item == 0 || buf.len() < item {
        return 0.0;
    }
    let per = (buf.len() / item).div_ceil(BLOCKS);
    let mut partial = [0.0f64; BLOCKS];
    partial
        .par_iter_mut()
        .zip(buf.par_chunks_mut(per * item))
        .enumerate()
        .for_each(|(b, (p, chunk))| {
            *p = chunk
                .chunks_exact_mut(item)
                .enumerate()
                .map(|(i, v)| f(b * per + i, v))
                .sum();
        });
    partial.iter().sum()
}

/// Pixels a per-pixel term takes at a time: up to 256, the most that divide the image, so that
/// the work per run (a closure call, a sum in f64) is spread thin and the loops over a run's
/// values vectorise.
pub(crate) fn run_pixels(pixels: usize) -> usize {
    (1..=pixels.min(256))
        .rev()
        .find(|d| pixels % d == 0)
        .unwrap_or(1)
}

/// Independent partial sums, so the loop vectorises (a single running sum cannot be reordered).
const LANES: usize = 8;

/// Sum of `f(i)` over `0..n` (called in order), in `LANES` partial sums of `Real` and then
/// with the tail in f64, in a fixed order: for the values of a run, short enough that `Real`
/// partial sums lose nothing that matters.
#[inline(always)]
pub(crate) fn lane_sum_of(n: usize, mut f: impl FnMut(usize) -> Real) -> f64 {
    let mut acc = [0.0 as Real; LANES];
    let full = n - n % LANES;
    for c in (0..full).step_by(LANES) {
        for (l, a) in acc.iter_mut().enumerate() {
            *a += f(c + l);
        }
    }
    let tail = (full..n).map(f);
    acc.into_iter().chain(tail).map(f64::from).sum()
}

/// Sum of `v`, in a fixed order ([`lane_sum_of`]).
pub(crate) fn lane_sum(v: &[Real]) -> f64 {
    lane_sum_of(v.len(), |i| v[i])
}

/// `lo + f (hi - lo)`: a value of a blended target (exactly `lo` where `f` is 0 and `lo`
/// finite).
#[inline(always)]
pub(crate) fn blend(lo: Real, hi: Real, f: Real) -> Real {
    lo + f * (hi - lo)
}

/// (a.a, b.b, a.b) of two equally long vectors, in a fixed order, with b the blend of `lo`
/// and `hi` by `f` (see [`blend`]).
pub(crate) fn dots(a: &[Real], lo: &[Real], hi: &[Real], f: Real) -> (Real, Real, Real) {
    let (mut aa, mut bb, mut ab) = (
        [0.0 as Real; LANES],
        [0.0 as Real; LANES],
        [0.0 as Real; LANES],
    );
    let n = a.len();
    let (lo, hi) = (&lo[..n], &hi[..n]);
    let full = n - n % LANES;
    for c in (0..full).step_by(LANES) {
        for i in 0..LANES {
            let (x, y) = (a[c + i], blend(lo[c + i], hi[c + i], f));
            aa[i] += x * x;
            bb[i] += y * y;
            ab[i] += x * y;
        }
    }
    let (mut s_aa, mut s_bb, mut s_ab): (Real, Real, Real) =
        (aa.iter().sum(), bb.iter().sum(), ab.iter().sum());
    for j in full..n {
        let (x, y) = (a[j], blend(lo[j], hi[j], f));
        s_aa += x * x;
        s_bb += y * y;
        s_ab += x * y;
    }
    (s_aa, s_bb, s_ab)
}
