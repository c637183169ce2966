//! Feature loss: mean over counted pixels of 1 - cos(rendered, target).

use super::{dots, pixel_counts, sum_items, Emit};
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
    cosine_into(rendered, target, channels, mask, grad, Emit::set(1.0))
}

pub(crate) fn cosine_into(
    rendered: &[Real],
    target: &[Real],
    channels: usize,
    mask: Option<&[bool]>,
    grad: &mut [Real],
    emit: Emit,
) -> Result<f64, String> {
    let counted = pixel_counts("feature loss", rendered, target, grad, mask, channels)?;
    let inv = if counted == 0 {
        0.0
    } else {
        1.0 / counted as Real
    };
    let sum = sum_items(grad, channels, |p, g| {
        if mask.is_some_and(|m| !m[p]) {
            g.iter_mut().for_each(|g| emit.put(g, 0.0));
            return 0.0;
        }
        let (r, t) = (
            &rendered[p * channels..][..channels],
            &target[p * channels..][..channels],
        );
        let (rr, tt, rt) = dots(r, t);
        let norm_r = rr.sqrt();
        let (nr, nt) = (norm_r.max(COS_EPS), tt.sqrt().max(COS_EPS));
        let cos = rt / (nr * nt);
        // d cos/dr = t / (nr nt) - cos r / |r|^2 while |r| > eps; the second part vanishes
        // where the norm is clamped.
        let a = 1.0 / (nr * nt);
        let b = if norm_r > COS_EPS { cos / rr } else { 0.0 };
        for ((g, &ri), &ti) in g.iter_mut().zip(r).zip(t) {
            emit.put(g, -inv * (a * ti - b * ri));
        }
        1.0 - f64::from(cos)
    });
    Ok(if counted == 0 {
        0.0
    } else {
        sum / counted as f64
    })
}
