//! Mean absolute error on colour (optionally masked) and on valid depth.
//!
//! The gradient of |d| at d = 0 is taken as 0 (as PyTorch's `sign`).

use rayon::prelude::*;

use super::{check_len, lane_sum_of, pixel_counts, run_pixels, sum_items, Emit};
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
    let run = run_pixels(rendered.len() / channels);
    let sum = sum_items(grad, run * channels, |i, g| {
        let at = i * g.len();
        let (r, t) = (&rendered[at..][..g.len()], &target[at..][..g.len()]);
        let Some(mask) = mask else {
            return lane_sum_of(g.len(), |j| {
                let d = r[j] - t[j];
                emit.put(&mut g[j], inv * sign(d));
                d.abs()
            });
        };
        let mut s = 0.0f64;
        for (p, &counts) in mask[i * run..][..run].iter().enumerate() {
            for j in p * channels..(p + 1) * channels {
                let d = r[j] - t[j];
                if counts {
                    s += f64::from(d.abs());
                }
                emit.put(&mut g[j], if counts { inv * sign(d) } else { 0.0 });
            }
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
    let counted = target.par_iter().filter(|&&z| valid_depth(z)).count();
    let inv = if counted == 0 {
        0.0
    } else {
        1.0 / counted as Real
    };
    let run = run_pixels(rendered.len());
    let sum = sum_items(grad, run, |i, g| {
        let at = i * run;
        let (r, t) = (&rendered[at..][..run], &target[at..][..run]);
        lane_sum_of(run, |j| {
            let (d, valid) = (r[j] - t[j], valid_depth(t[j]));
            emit.put(&mut g[j], if valid { inv * sign(d) } else { 0.0 });
            if valid {
                d.abs()
            } else {
                0.0
            }
        })
    });
    Ok(if counted == 0 {
        0.0
    } else {
        sum / counted as f64
    })
}
