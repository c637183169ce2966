//! Feature loss: mean over counted pixels of 1 - cos(rendered, target).

use super::{blend, dots, pixel_counts, run_pixels, sum_items, Emit, FeatureTarget};
use crate::Real;

/// Norms below this are clamped to it: cos = r.t / (max(|r|, eps) max(|t|, eps)).
/// For |r| <= eps the cosine is therefore linear in r and its gradient is t / (eps max(|t|,
/// eps)), which is large: a pixel whose rendered feature is (near) zero pulls hard along the
/// target. A zero target gives cos = 0 (loss 1) with zero gradient; mask such pixels out.
pub const COS_EPS: Real = 1e-6;

/// Mean of 1 - cos(r, t) over the pixels where `mask` is true (all without a mask), with r and
/// t the `channels`-vectors of `rendered` and `target` at a pixel; `grad` receives
/// d(mean)/d(rendered), 0 on masked-out pixels. Returns 0 when no pixel counts.
pub fn cosine(
    rendered: &[Real],
    target: &[Real],
    channels: usize,
    mask: Option<&[bool]>,
    grad: &mut [Real],
) -> Result<f64, String> {
    let target = FeatureTarget::Pixels(target);
    cosine_into(rendered, target, channels, mask, grad, Emit::set(1.0))
}

/// A target's rows of `row` values each: per pixel row, the values it starts from, the values
/// it blends towards and by how much (a row of a per-pixel target blends nothing).
struct Rows<'a> {
    target: FeatureTarget<'a>,
    row: usize,
}

impl Rows<'_> {
    /// Pixel row `y`'s (lower, upper, weight).
    #[inline(always)]
    fn get(&self, y: usize) -> (&[Real], &[Real], Real) {
        match self.target {
            FeatureTarget::Pixels(t) => {
                let r = &t[y * self.row..][..self.row];
                (r, r, 0.0)
            }
            FeatureTarget::Blended { rows, blends } => {
                let b = blends[y];
                let at = |i: usize| &rows[i * self.row..][..self.row];
                (at(b.lower), at(b.upper), b.weight)
            }
        }
    }
}

/// Checks `target` against a `pixels`-pixel rendered map of `channels` channels and returns
/// how many pixels make one of its rows. A per-pixel target has no rows of its own: it is
/// read in runs ([`run_pixels`]).
fn row_pixels(target: FeatureTarget, pixels: usize, channels: usize) -> Result<usize, String> {
    let FeatureTarget::Blended { rows, blends } = target else {
        // `pixel_counts` checked a per-pixel target's length.
        return Ok(run_pixels(pixels));
    };
    if blends.is_empty() || pixels % blends.len() != 0 {
        return Err(format!(
            "feature loss: {} blended target rows cannot cover a {pixels}-pixel image",
            blends.len()
        ));
    }
    let row = pixels / blends.len() * channels;
    if row == 0 || rows.len() % row != 0 {
        return Err(format!(
            "feature loss: the target's rows hold {} values, not a whole number of rows of {row}",
            rows.len()
        ));
    }
    let n = rows.len() / row;
    if let Some(b) = blends
        .iter()
        .find(|b| b.lower >= n || b.upper >= n || !(0.0..=1.0).contains(&b.weight))
    {
        return Err(format!(
            "feature loss: a blend of target rows {} and {} by {} is out of range for {n} rows",
            b.lower, b.upper, b.weight
        ));
    }
    Ok(pixels / blends.len())
}

pub(crate) fn cosine_into(
    rendered: &[Real],
    target: FeatureTarget,
    channels: usize,
    mask: Option<&[bool]>,
    grad: &mut [Real],
    emit: Emit,
) -> Result<f64, String> {
    let target_len = match target {
        FeatureTarget::Pixels(t) => Some(t.len()),
        FeatureTarget::Blended { .. } => None,
    };
    let counted = pixel_counts("feature loss", rendered, target_len, grad, mask, channels)?;
    let per_row = row_pixels(target, rendered.len() / channels, channels)?;
    let row = per_row * channels;
    let rows = Rows { target, row };
    let inv = if counted == 0 {
        0.0
    } else {
        1.0 / counted as Real
    };
    let sum = sum_items(grad, row, |y, g| {
        let (lo, hi, f) = rows.get(y);
        let pixels = PixelRun {
            rendered: &rendered[y * row..][..row],
            lo,
            hi,
            f,
            mask: mask.map(|m| &m[y * per_row..][..per_row]),
        };
        pixels.run(channels, inv, emit, g)
    });
    Ok(if counted == 0 {
        0.0
    } else {
        sum / counted as f64
    })
}

/// A run of pixels: rendered vectors, their targets `lo + f (hi - lo)` and which count.
struct PixelRun<'a> {
    rendered: &'a [Real],
    lo: &'a [Real],
    hi: &'a [Real],
    f: Real,
    mask: Option<&'a [bool]>,
}

impl PixelRun<'_> {
    /// Sum of 1 - cos over the counted pixels; `scale * d(1 - cos)/d(rendered)` emitted into
    /// `g` (zero where not counted).
    #[inline(always)]
    fn run(self, k: usize, scale: Real, emit: Emit, g: &mut [Real]) -> f64 {
        let f = self.f;
        let mut sum = 0.0;
        for (p, g) in g.chunks_exact_mut(k).enumerate() {
            if self.mask.is_some_and(|m| !m[p]) {
                g.iter_mut().for_each(|g| emit.put(g, 0.0));
                continue;
            }
            let (r, lo, hi) = (
                &self.rendered[p * k..][..k],
                &self.lo[p * k..][..k],
                &self.hi[p * k..][..k],
            );
            let (rr, tt, rt) = dots(r, lo, hi, f);
            let norm_r = rr.sqrt();
            let (nr, nt) = (norm_r.max(COS_EPS), tt.sqrt().max(COS_EPS));
            let cos = rt / (nr * nt);
            // d cos/dr = t / (nr nt) - cos r / |r|^2 while |r| > eps; the second part vanishes
            // where the norm is clamped.
            let a = 1.0 / (nr * nt);
            let b = if norm_r > COS_EPS { cos / rr } else { 0.0 };
            for (((g, &ri), &l), &h) in g.iter_mut().zip(r).zip(lo).zip(hi) {
                emit.put(g, -scale * (a * blend(l, h, f) - b * ri));
            }
            sum += 1.0 - f64::from(cos);
        }
        sum
    }
}
