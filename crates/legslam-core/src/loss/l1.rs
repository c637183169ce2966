//! Mean absolute error on colour (optionally masked) and on valid depth.
//!
//! The gradient of |d| at d = 0 is taken as 0 (as PyTorch's `sign`).

use super::{check_len, pixel_counts, sum_items, Emit};
use crate::Real;

#[inline]
fn sign(d: Real) -> Real {
    if d > 0.0 {
        1.0
    } else if d < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// Mean |rendered - target| over every value of the pixels where `mask` is true (all pixels
/// without a mask); `grad` receives d(mean)/d(rendered), 0 on masked-out pixels. Returns 0
/// when no pixel counts.
pub fn l1(
    rendered: &[Real],
    target: &[Real],
    mask: Option<&[bool]>,
    channels: usize,
    grad: &mut [Real],
) -> Result<f64, String> {
    l1_into(rendered, target, mask, channels, grad, Emit::set(1.0))
}

pub(crate) fn l1_into(
    rendered: &[Real],
    target: &[Real],
    mask: Option<&[bool]>,
    channels: usize,
    grad: &mut [Real],
    emit: Emit,
) -> Result<f64, String> {
    let counted = pixel_counts("L1", rendered, Some(target.len()), grad, mask, channels)?;
    let counted = counted * channels;
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
        let mut s = 0.0f64;
        for ((g, &r), &t) in g.iter_mut().zip(r).zip(t) {
            let d = r - t;
            s += f64::from(d.abs());
            emit.put(g, inv * sign(d));
        }
        s
    });
    Ok(if counted == 0 {
        0.0
    } else {
        sum / counted as f64
    })
}

/// Mean |rendered - target| over pixels whose target depth is finite and > 0 (0 if none);
/// `grad` receives d(mean)/d(rendered), 0 on invalid pixels.
pub fn depth_l1(rendered: &[Real], target: &[Real], grad: &mut [Real]) -> Result<f64, String> {
    depth_l1_into(rendered, target, grad, Emit::set(1.0))
}

#[inline]
fn valid_depth(z: Real) -> bool {
    z > 0.0 && z.is_finite()
}

pub(crate) fn depth_l1_into(
    rendered: &[Real],
    target: &[Real],
    grad: &mut [Real],
    emit: Emit,
) -> Result<f64, String> {
    check_len("target depth", target.len(), rendered.len())?;
    check_len("depth gradient buffer", grad.len(), rendered.len())?;
    let counted = target.iter().filter(|&&z| valid_depth(z)).count();
    let inv = if counted == 0 {
        0.0
    } else {
        1.0 / counted as Real
    };
    let sum = sum_items(grad, 1, |p, g| {
        let (r, t) = (rendered[p], target[p]);
        if !valid_depth(t) {
            emit.put(&mut g[0], 0.0);
            return 0.0;
        }
        emit.put(&mut g[0], inv * sign(r - t));
        f64::from((r - t).abs())
    });
    Ok(if counted == 0 {
        0.0
    } else {
        sum / counted as f64
    })
}
