//! SSIM in the 3D Gaussian Splatting form and its gradient with respect to the rendered image.
//!
//! Per channel, with G the 11x11 Gaussian window (sigma 1.5, normalised to sum 1) applied as a
//! 'same'-size correlation with ZERO padding (PyTorch `F.conv2d(..., padding=5)`, as in the
//! 3DGS `ssim()`): mu_x = G*x, s_xx = G*(x^2) - mu_x^2, s_xy = G*(xy) - mu_x mu_y, and
//! SSIM = mean over pixels and channels of
//! (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_xx + s_yy + C2)),
//! C1 = 0.01^2, C2 = 0.03^2. Near the border the window's weights inside the image sum to less
//! than one; that is the 3DGS behaviour (scikit-image instead reflects and crops a 5-pixel
//! border; the two agree on pixels at least 5 from every edge).
//!
//! The window is separable, so every filter is a horizontal then a vertical 1-D pass. With
//! zero padding the filter is self-adjoint, which makes the backward pass three more filters:
//! dSSIM/dx = G*(dS/dmu_x) + 2x G*(dS/dE[x^2]) + y G*(dS/dE[xy]).

use rayon::prelude::*;

use super::{check_len, sum_items, Emit};
use crate::Real;

const RADIUS: usize = 5;
const SIGMA: f64 = 1.5;
const C1: Real = 0.01 * 0.01;
const C2: Real = 0.03 * 0.03;

/// The 1-D window's weights at offsets 0..=RADIUS (it is symmetric).
fn kernel() -> [Real; RADIUS + 1] {
    let g = |d: usize| (-((d * d) as f64) / (2.0 * SIGMA * SIGMA)).exp();
    let total: f64 = (1..=RADIUS).map(|d| 2.0 * g(d)).sum::<f64>() + 1.0;
    std::array::from_fn(|d| (g(d) / total) as Real)
}

/// Reusable SSIM workspace: two buffers of five image-sized maps, grown on demand.
#[derive(Debug, Default)]
pub struct Ssim {
    horizontal: Vec<Real>,
    vertical: Vec<Real>,
}

impl Ssim {
    pub fn new() -> Self {
        Self::default()
    }

    /// Mean SSIM of `x` against `y`, both row-major channel-last `width x height x channels`.
    pub fn value(
        &mut self,
        x: &[Real],
        y: &[Real],
        width: usize,
        height: usize,
        channels: usize,
    ) -> Result<f64, String> {
        self.run(x, y, (width, height, channels), None)
    }

    /// Mean SSIM, and d(SSIM)/d(x) written into `grad` (same layout as `x`).
    pub fn value_and_grad(
        &mut self,
        x: &[Real],
        y: &[Real],
        width: usize,
        height: usize,
        channels: usize,
        grad: &mut [Real],
    ) -> Result<f64, String> {
        let emit = Emit {
            scale: 1.0,
            add: false,
        };
        self.run(x, y, (width, height, channels), Some((grad, emit)))
    }

    /// The whole computation; with `grad`, emits `scale * dSSIM/dx` into it (set or add).
    pub(crate) fn run(
        &mut self,
        x: &[Real],
        y: &[Real],
        (width, height, channels): (usize, usize, usize),
        grad: Option<(&mut [Real], Emit)>,
    ) -> Result<f64, String> {
        let n = width * height * channels;
        if n == 0 {
            return Err(format!(
                "SSIM needs a non-empty image, got {width} x {height} x {channels}"
            ));
        }
        check_len("SSIM rendered image", x.len(), n)?;
        check_len("SSIM target image", y.len(), n)?;
        if let Some((g, _)) = &grad {
            check_len("SSIM gradient buffer", g.len(), n)?;
        }
        let row = width * channels;
        // Each image row owns five maps of `row` values: [row][map][column, channel].
        self.horizontal.resize(5 * n, 0.0);
        self.vertical.resize(5 * n, 0.0);
        let k = kernel();
        let inv_n = 1.0 / n as Real;
        let want_grad = grad.is_some();

        // Products into the vertical buffer (free for now), then horizontal filters.
        self.horizontal
            .par_chunks_mut(5 * row)
            .zip(self.vertical.par_chunks_mut(5 * row))
            .enumerate()
            .for_each(|(r, (h, v))| {
                let (xs, ys) = (&x[r * row..][..row], &y[r * row..][..row]);
                let (vx, rest) = v.split_at_mut(row);
                let (vy, rest) = rest.split_at_mut(row);
                let (vxx, rest) = rest.split_at_mut(row);
                let (vyy, vxy) = rest.split_at_mut(row);
                for j in 0..row {
                    let (a, b) = (xs[j], ys[j]);
                    vx[j] = a;
                    vy[j] = b;
                    vxx[j] = a * a;
                    vyy[j] = b * b;
                    vxy[j] = a * b;
                }
                for (hm, vm) in h.chunks_exact_mut(row).zip(v.chunks_exact(row)) {
                    filter_line(&k, vm, hm, channels);
                }
            });

        // Vertical filters, then per pixel the SSIM and its derivatives with respect to the
        // three filtered maps that depend on x, stored over the first three maps.
        let horizontal = &self.horizontal;
        let total = sum_items(&mut self.vertical, 5 * row, |r, v| {
            filter_column(&k, horizontal, 5 * row, height, r, v);
            // Buffer order x, y, xx, yy, xy; the derivatives overwrite maps 0, 1, 2 in place.
            let (mx, rest) = v.split_at_mut(row);
            let (my, rest) = rest.split_at_mut(row);
            let (exx, rest) = rest.split_at_mut(row);
            let (eyy, exy) = rest.split_at_mut(row);
            let mut sum = 0.0f64;
            for j in 0..row {
                let (ux, uy) = (mx[j], my[j]);
                let sxx = exx[j] - ux * ux;
                let syy = eyy[j] - uy * uy;
                let sxy = exy[j] - ux * uy;
                let a1 = 2.0 * ux * uy + C1;
                let a2 = 2.0 * sxy + C2;
                let b1 = ux * ux + uy * uy + C1;
                let b2 = sxx + syy + C2;
                let inv = 1.0 / (b1 * b2);
                let s = a1 * a2 * inv;
                sum += f64::from(s);
                if want_grad {
                    // dS/dA1 = A2 inv, dS/dA2 = A1 inv, dS/dB1 = -S/B1 = -S B2 inv,
                    // dS/dB2 = -S/B2 = -S B1 inv (no further divisions).
                    let d_a1 = a2 * inv;
                    let d_a2 = a1 * inv;
                    let d_b2 = -s * b1 * inv;
                    mx[j] = inv_n * (2.0 * uy * (d_a1 - d_a2) + 2.0 * ux * s * (b1 - b2) * inv);
                    my[j] = inv_n * d_b2;
                    exx[j] = inv_n * (2.0 * d_a2);
                }
            }
            sum
        });
        let Some((grad, emit)) = grad else {
            return Ok(total / n as f64);
        };
        // Maps 0, 1, 2 now hold dS/d(mu_x), dS/d(E[x^2]), dS/d(E[xy]): filter them back.
        self.horizontal
            .par_chunks_mut(5 * row)
            .zip(self.vertical.par_chunks(5 * row))
            .for_each(|(h, v)| {
                for (hm, vm) in h.chunks_exact_mut(row).zip(v.chunks_exact(row)).take(3) {
                    filter_line(&k, vm, hm, channels);
                }
            });
        let horizontal = &self.horizontal;
        self.vertical
            .par_chunks_mut(5 * row)
            .zip(grad.par_chunks_mut(row))
            .enumerate()
            .for_each(|(r, (v, g))| {
                let v = &mut v[..3 * row];
                filter_column(&k, horizontal, 5 * row, height, r, v);
                let (xs, ys) = (&x[r * row..][..row], &y[r * row..][..row]);
                let (dm, rest) = v.split_at(row);
                let (dxx, dxy) = rest.split_at(row);
                for j in 0..row {
                    emit.put(&mut g[j], dm[j] + 2.0 * xs[j] * dxx[j] + ys[j] * dxy[j]);
                }
            });
        Ok(total / n as f64)
    }
}

/// `out = window (*) inp` along one image row whose pixels are `stride` values apart, with
/// zeros beyond the row's ends. Each tap is a shifted contiguous slice, so the loops vectorise.
fn filter_line(k: &[Real; RADIUS + 1], inp: &[Real], out: &mut [Real], stride: usize) {
    let n = inp.len();
    for (o, &v) in out.iter_mut().zip(inp) {
        *o = k[0] * v;
    }
    for (d, &w) in k.iter().enumerate().skip(1) {
        let s = d * stride;
        if s >= n {
            break;
        }
        // Right neighbour for j < n - s, left neighbour for j >= s.
        for (o, &v) in out[..n - s].iter_mut().zip(&inp[s..]) {
            *o += w * v;
        }
        for (o, &v) in out[s..].iter_mut().zip(&inp[..n - s]) {
            *o += w * v;
        }
    }
}

/// `out = window (*) column` for image row `r`: the weighted sum of the rows `r - 5 ..= r + 5`
/// that exist, each `out.len()` values starting at `row * row_stride` in `buf`.
fn filter_column(
    k: &[Real; RADIUS + 1],
    buf: &[Real],
    row_stride: usize,
    height: usize,
    r: usize,
    out: &mut [Real],
) {
    let len = out.len();
    let row = |i: usize| &buf[i * row_stride..][..len];
    for (o, &v) in out.iter_mut().zip(row(r)) {
        *o = k[0] * v;
    }
    for (d, &w) in k.iter().enumerate().skip(1) {
        match (r.checked_sub(d), r + d < height) {
            (Some(up), true) => {
                for ((o, &a), &b) in out.iter_mut().zip(row(up)).zip(row(r + d)) {
                    *o += w * (a + b);
                }
            }
            (Some(up), false) => {
                for (o, &a) in out.iter_mut().zip(row(up)) {
                    *o += w * a;
                }
            }
            (None, true) => {
                for (o, &b) in out.iter_mut().zip(row(r + d)) {
                    *o += w * b;
                }
            }
            (None, false) => {}
        }
    }
}
