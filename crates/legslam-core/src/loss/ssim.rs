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

use super::{check_len, lane_sum, sum_items, Emit};
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

/// Reusable SSIM workspace, grown on demand: per image row, five lines with zero margins
/// (inputs of the horizontal filter) and five horizontal results; and a zero line standing in
/// for rows beyond the image. The vertical results are used where they are made, a row at a
/// time (as whole images they were 5 more maps written and read back, past the caches).
#[derive(Debug)]
pub struct Ssim {
    padded: Vec<Real>,
    horizontal: Vec<Real>,
    zeros: Vec<Real>,
    shape: (usize, usize, usize),
    /// The per-row loops compiled for AVX2 (eight values an instruction instead of the
    /// baseline's four): the same operations in the same order, so the same bits.
    avx2: bool,
}

impl Default for Ssim {
    fn default() -> Self {
        Self::with_avx2(crate::raster::avx2_available())
    }
}

impl Ssim {
    pub fn new() -> Self {
        Self::default()
    }

    /// With `avx2` false, the baseline loops even where the CPU has AVX2 (the reference the
    /// tests and the loss bench compare the fast path with); true is ignored where it has not.
    pub fn with_avx2(avx2: bool) -> Self {
        Ssim {
            padded: Vec::new(),
            horizontal: Vec::new(),
            zeros: Vec::new(),
            shape: (0, 0, 0),
            avx2: avx2 && crate::raster::avx2_available(),
        }
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
        self.run(
            x,
            y,
            (width, height, channels),
            Some((grad, Emit::set(1.0))),
        )
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
        let margin = RADIUS * channels;
        let line = row + 2 * margin;
        if self.shape != (width, height, channels) {
            // Margins are never written, so they stay zero only if cleared on a new shape.
            self.padded.clear();
            self.shape = (width, height, channels);
        }
        self.padded.resize(5 * line * height, 0.0);
        self.horizontal.resize(5 * n, 0.0);
        self.zeros.resize(row, 0.0);
        let k = kernel();
        let inv_n = 1.0 / n as Real;
        let avx2 = self.avx2;

        // Maps x, y, xx, yy, xy into the padded lines, then horizontal filters.
        self.padded
            .par_chunks_mut(5 * line)
            .zip(self.horizontal.par_chunks_mut(5 * row))
            .enumerate()
            .for_each(|(r, (p, h))| {
                let (xs, ys) = (&x[r * row..][..row], &y[r * row..][..row]);
                let mut lines = p.chunks_exact_mut(line).map(|l| &mut l[margin..][..row]);
                let mut next = || lines.next().unwrap_or_default();
                let (px, py, pxx, pyy, pxy) = (next(), next(), next(), next(), next());
                let (px, py, pxx) = (&mut px[..row], &mut py[..row], &mut pxx[..row]);
                let (pyy, pxy) = (&mut pyy[..row], &mut pxy[..row]);
                for j in 0..row {
                    let (a, b) = (xs[j], ys[j]);
                    px[j] = a;
                    py[j] = b;
                    pxx[j] = a * a;
                    pyy[j] = b * b;
                    pxy[j] = a * b;
                }
                for (pl, hl) in p.chunks_exact(line).zip(h.chunks_exact_mut(row)) {
                    filter_line(avx2, &k, pl, hl, channels);
                }
            });

        // Vertical filters, then per pixel the SSIM and its derivatives with respect to the
        // three filtered maps that depend on x, written into padded lines 0, 1, 2 (free now).
        let (horizontal, zeros) = (&self.horizontal, &self.zeros[..]);
        let total = sum_items(&mut self.padded, 5 * line, |r, p| {
            // The row's five vertical results (tens of kB, allocated per row: the summing
            // helper keeps no per-thread state).
            let mut v = vec![0.0; 5 * row];
            for (m, out) in v.chunks_exact_mut(row).enumerate() {
                let map = (&horizontal[..], 5 * row, m * row);
                filter_column(avx2, &k, map, zeros, height, r, out);
            }
            let mut maps = v.chunks_exact_mut(row);
            let mut next = || maps.next().unwrap_or_default();
            let (mx, my, exx, eyy, exy) = (next(), next(), next(), next(), next());
            let mut lines = p.chunks_exact_mut(line).map(|l| &mut l[margin..][..row]);
            let mut next = || lines.next().unwrap_or_default();
            let (d_mx, d_exx, d_exy) = (next(), next(), next());
            let stats = Stats {
                mx,
                my,
                exx,
                eyy,
                exy,
                d_mx,
                d_exx,
                d_exy,
            };
            stats.run(avx2, inv_n);
            lane_sum(exy)
        });
        let Some((grad, emit)) = grad else {
            return Ok(total / n as f64);
        };
        // Filter dS/d(mu_x), dS/d(E[x^2]), dS/d(E[xy]) back (the filter is self-adjoint).
        self.padded
            .par_chunks(5 * line)
            .zip(self.horizontal.par_chunks_mut(5 * row))
            .for_each(|(p, h)| {
                for (pl, hl) in p.chunks_exact(line).zip(h.chunks_exact_mut(row)).take(3) {
                    filter_line(avx2, &k, pl, hl, channels);
                }
            });
        let horizontal = &self.horizontal;
        grad.par_chunks_mut(row).enumerate().for_each_init(
            || vec![0.0; 3 * row],
            |v, (r, g)| {
                for (m, out) in v.chunks_exact_mut(row).enumerate() {
                    let map = (&horizontal[..], 5 * row, m * row);
                    filter_column(avx2, &k, map, zeros, height, r, out);
                }
                let (xs, ys) = (&x[r * row..][..row], &y[r * row..][..row]);
                let (dm, rest) = v.split_at(row);
                let (dxx, dxy) = rest.split_at(row);
                chain(avx2, emit, [dm, dxx, &dxy[..row], xs, ys], &mut g[..row]);
            },
        );
        Ok(total / n as f64)
    }
}

/// Calls `$plain($args)`, or `$fast($args)`, the same body compiled for AVX2, where `$avx2`
/// (`Ssim::with_avx2` keeps it false on a CPU without AVX2).
macro_rules! dispatch {
    ($avx2:expr, $fast:ident, $plain:path, ($($arg:expr),*)) => {{
        #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
        if $avx2 {
            // SAFETY: `avx2` holds only where the CPU has AVX2.
            return unsafe { $fast($($arg),*) };
        }
        let _ = $avx2;
        $plain($($arg),*)
    }};
}

/// `out[j] = k0 c[j] + sum_d k_d (before_d[j] + after_d[j])`: the symmetric window applied to
/// eleven equally long input slices, one output write per value (vectorises).
#[inline(always)]
fn window_sum(k: &[Real; RADIUS + 1], taps: [&[Real]; 2 * RADIUS + 1], out: &mut [Real]) {
    let n = out.len();
    let [b5, b4, b3, b2, b1, c, a1, a2, a3, a4, a5] = taps.map(|t| &t[..n]);
    for (j, o) in out.iter_mut().enumerate() {
        *o = k[0] * c[j]
            + k[1] * (b1[j] + a1[j])
            + k[2] * (b2[j] + a2[j])
            + k[3] * (b3[j] + a3[j])
            + k[4] * (b4[j] + a4[j])
            + k[5] * (b5[j] + a5[j]);
    }
}

/// Horizontal filter of one image row: `padded` holds the row's values with `RADIUS` zero
/// pixels on each side, pixels `stride` values apart; `out` gets the filtered row.
fn filter_line(
    avx2: bool,
    k: &[Real; RADIUS + 1],
    padded: &[Real],
    out: &mut [Real],
    stride: usize,
) {
    let n = out.len();
    let taps = std::array::from_fn(|o| &padded[o * stride..][..n]);
    dispatch!(avx2, window_sum_avx2, window_sum, (k, taps, out))
}

/// Vertical filter for image row `r` of the map starting `offset` values into each row of
/// `buf` (`(buf, row_stride, offset)`); rows beyond the image read as `zeros`.
fn filter_column(
    avx2: bool,
    k: &[Real; RADIUS + 1],
    (buf, row_stride, offset): (&[Real], usize, usize),
    zeros: &[Real],
    height: usize,
    r: usize,
    out: &mut [Real],
) {
    let n = out.len();
    let taps = std::array::from_fn(|o| match (r + o).checked_sub(RADIUS) {
        Some(i) if i < height => &buf[i * row_stride + offset..][..n],
        _ => &zeros[..n],
    });
    dispatch!(avx2, window_sum_avx2, window_sum, (k, taps, out))
}

/// [`window_sum`] compiled for AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
#[target_feature(enable = "avx2")]
unsafe fn window_sum_avx2(
    k: &[Real; RADIUS + 1],
    taps: [&[Real]; 2 * RADIUS + 1],
    out: &mut [Real],
) {
    window_sum(k, taps, out)
}

/// One row of the filtered maps (means, second moments) in, the SSIM map (over `exy`, used up)
/// and its derivatives with respect to the three maps that depend on x out.
struct Stats<'a> {
    mx: &'a [Real],
    my: &'a [Real],
    exx: &'a [Real],
    eyy: &'a [Real],
    exy: &'a mut [Real],
    d_mx: &'a mut [Real],
    d_exx: &'a mut [Real],
    d_exy: &'a mut [Real],
}

impl Stats<'_> {
    fn run(self, avx2: bool, inv_n: Real) {
        dispatch!(avx2, stats_avx2, Stats::body, (self, inv_n))
    }

    #[inline(always)]
    fn body(self, inv_n: Real) {
        let n = self.exy.len();
        // Equal, known lengths let the loop drop its bounds checks and vectorise.
        let (mx, my, exx, eyy) = (&self.mx[..n], &self.my[..n], &self.exx[..n], &self.eyy[..n]);
        let (d_mx, d_exx, d_exy) = (
            &mut self.d_mx[..n],
            &mut self.d_exx[..n],
            &mut self.d_exy[..n],
        );
        let exy = self.exy;
        for j in 0..n {
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
            // E[xy] is used up: keep the SSIM map in its place for the sum.
            exy[j] = s;
            // Derivatives even for the value alone: a branch here would stop vectorisation.
            // dS/dA1 = A2 inv, dS/dA2 = A1 inv, dS/dB1 = -S/B1 = -S B2 inv,
            // dS/dB2 = -S/B2 = -S B1 inv (no further divisions).
            let d_a1 = a2 * inv;
            let d_a2 = a1 * inv;
            d_mx[j] = inv_n * (2.0 * uy * (d_a1 - d_a2) + 2.0 * ux * s * (b1 - b2) * inv);
            d_exx[j] = inv_n * (-s * b1 * inv);
            d_exy[j] = inv_n * (2.0 * d_a2);
        }
    }
}

/// [`Stats::body`] compiled for AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
#[target_feature(enable = "avx2")]
unsafe fn stats_avx2(stats: Stats, inv_n: Real) {
    stats.body(inv_n)
}

/// The chain rule back to x for one row: `g = dS/dmu_x + 2x dS/dE[x^2] + y dS/dE[xy]` from
/// the filtered derivatives and the row's `x`, `y` (`[dm, dxx, dxy, x, y]`), emitted into `g`.
fn chain(avx2: bool, emit: Emit, maps: [&[Real]; 5], g: &mut [Real]) {
    dispatch!(avx2, chain_avx2, chain_body, (emit, maps, g))
}

#[inline(always)]
fn chain_body(emit: Emit, [dm, dxx, dxy, xs, ys]: [&[Real]; 5], g: &mut [Real]) {
    let n = g.len();
    let (dm, dxx, dxy, xs, ys) = (&dm[..n], &dxx[..n], &dxy[..n], &xs[..n], &ys[..n]);
    for j in 0..n {
        emit.put(&mut g[j], dm[j] + 2.0 * xs[j] * dxx[j] + ys[j] * dxy[j]);
    }
}

/// [`chain_body`] compiled for AVX2.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
#[target_feature(enable = "avx2")]
unsafe fn chain_avx2(emit: Emit, maps: [&[Real]; 5], g: &mut [Real]) {
    chain_body(emit, maps, g)
}
