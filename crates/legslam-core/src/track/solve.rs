//! Residuals, their Jacobians, and the deterministic parallel reduction of the normal
//! equations.
//!
//! We estimate `T_rf`, the pose of the frame in the reference camera. Each frame pixel with
//! valid depth gives a point `X_f`, moved to `X = R X_f + t` in the reference camera and
//! projected to `(u, v)` there (projective data association):
//!
//! - geometric (point-to-plane) residual `r_g = n . (X - V)` with the reference vertex `V`
//!   and normal `n` at the nearest pixel; Jacobian `[n, X x n]`;
//! - photometric residual `r_p = I_r(u, v) - I_f(p)` with `I_r` and its gradient bilinearly
//!   interpolated; Jacobian `[g, X x g]` with `g = (gx fx / z, gy fy / z,
//!   -(gx fx x + gy fy y) / z^2)`.
//!
//! Both use the left perturbation `T_rf <- exp(delta) T_rf` of [`crate::camera::se3`].

use rayon::prelude::*;

use super::image::Level;
use super::TrackerConfig;

/// Rows of the frame image per reduction chunk. Fixed, so that the floating-point summation
/// order (and with it the result) does not depend on rayon's work splitting.
const ROWS_PER_CHUNK: usize = 4;

/// Sums of one pass over the frame: normal equations and statistics.
#[derive(Clone, Debug, Default)]
pub(crate) struct Sums {
    /// Upper triangle of `J^T W J`, row-major.
    pub h: [f64; 21],
    /// `J^T W r`.
    pub b: [f64; 6],
    /// Robust cost.
    pub cost: f64,
    /// Frame pixels with valid depth.
    pub n_valid: u64,
    /// Geometric / photometric residuals used.
    pub n_geo: u64,
    pub n_photo: u64,
    /// Geometric residuals within the inlier threshold.
    pub n_inlier: u64,
    /// Sums of squared raw geometric (inliers) and photometric residuals.
    pub sq_geo: f64,
    pub sq_photo: f64,
    /// Sum of the depths of the geometric correspondences (for the condition scaling).
    pub depth_sum: f64,
    /// Sums of the reference and (raw) frame intensities of the photometric terms (for the
    /// exposure gain).
    pub sum_ir: f64,
    pub sum_if: f64,
}

impl Sums {
    fn add(&mut self, o: &Sums) {
        for (a, b) in self.h.iter_mut().zip(o.h.iter()) {
            *a += b;
        }
        for (a, b) in self.b.iter_mut().zip(o.b.iter()) {
            *a += b;
        }
        self.cost += o.cost;
        self.n_valid += o.n_valid;
        self.n_geo += o.n_geo;
        self.n_photo += o.n_photo;
        self.n_inlier += o.n_inlier;
        self.sq_geo += o.sq_geo;
        self.sq_photo += o.sq_photo;
        self.depth_sum += o.depth_sum;
        self.sum_ir += o.sum_ir;
        self.sum_if += o.sum_if;
    }
}

/// Row accumulator in f32 (one row is at most a few thousand terms), flushed into f64.
/// Row `i` of `h` holds `sum w J_i [J, r, 0]`: the full 6x6 block plus `b` in column 6, laid
/// out 8 wide so that the update vectorises.
#[derive(Default)]
struct RowAcc {
    h: [[f32; 8]; 6],
    cost: f32,
    sq_geo: f32,
    sq_photo: f32,
    depth_sum: f32,
    sum_ir: f32,
    sum_if: f32,
}

impl RowAcc {
    #[inline(always)]
    fn add(&mut self, j: &[f32; 6], r: f32, w: f32) {
        let jr = [j[0], j[1], j[2], j[3], j[4], j[5], r, 0.0];
        for (row, &ji) in self.h.iter_mut().zip(j.iter()) {
            let a = w * ji;
            for (hk, &jk) in row.iter_mut().zip(jr.iter()) {
                *hk += a * jk;
            }
        }
    }

    fn flush(&mut self, s: &mut Sums) {
        let mut k = 0;
        for i in 0..6 {
            for jj in i..6 {
                s.h[k] += self.h[i][jj] as f64;
                k += 1;
            }
            s.b[i] += self.h[i][6] as f64;
        }
        s.cost += self.cost as f64;
        s.sq_geo += self.sq_geo as f64;
        s.sq_photo += self.sq_photo as f64;
        s.depth_sum += self.depth_sum as f64;
        s.sum_ir += self.sum_ir as f64;
        s.sum_if += self.sum_if as f64;
        *self = RowAcc::default();
    }
}

/// The reference side of one pyramid level.
pub(crate) struct RefLevel<'a> {
    pub lev: &'a Level,
    pub igd: &'a [[f32; 4]],
    pub normals: &'a [[f32; 4]],
}

/// Residual parameters of a pass, in f32.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Params {
    pub max_depth_diff: f32,
    pub inv_huber_g: f32,
    pub inv_huber_p: f32,
    pub photo_weight: f32,
    pub min_grad_sq: f32,
    pub inlier_threshold: f32,
    /// Exposure gain applied to the frame intensity: `r_p = I_r - gain * I_f`.
    pub gain: f32,
}

impl Params {
    pub fn new(c: &TrackerConfig) -> Params {
        Params {
            max_depth_diff: c.max_depth_diff as f32,
            inv_huber_g: (1.0 / c.geometric_huber) as f32,
            inv_huber_p: (1.0 / c.photometric_huber) as f32,
            photo_weight: c.photometric_weight as f32,
            min_grad_sq: (c.min_gradient * c.min_gradient) as f32,
            inlier_threshold: c.inlier_threshold as f32,
            gain: 1.0,
        }
    }
}

/// The residuals of one frame pixel (`None` when it has no correspondence).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct PixelResiduals {
    /// Point-to-plane residual (m), its Jacobian, and the depth of the point.
    pub geo: Option<(f32, [f32; 6], f32)>,
    /// Intensity residual, its Jacobian, and the interpolated reference intensity.
    pub photo: Option<(f32, [f32; 6], f32)>,
    /// Index of the associated reference pixel (nearest), for tests.
    pub pixel: usize,
}

#[inline(always)]
fn cross(a: &[f32; 3], b: &[f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Residuals of the frame point `xf` (frame camera) under `T_rf = (rot, t)`.
#[inline(always)]
pub(crate) fn eval_point(
    r: &RefLevel<'_>,
    xf: &[f32; 3],
    intensity_f: f32,
    rot: &[[f32; 3]; 3],
    t: &[f32; 3],
    p: &Params,
) -> PixelResiduals {
    let mut out = PixelResiduals::default();
    let x = [
        rot[0][0] * xf[0] + rot[0][1] * xf[1] + rot[0][2] * xf[2] + t[0],
        rot[1][0] * xf[0] + rot[1][1] * xf[1] + rot[1][2] * xf[2] + t[1],
        rot[2][0] * xf[0] + rot[2][1] * xf[1] + rot[2][2] * xf[2] + t[2],
    ];
    if x[2] <= 1e-3 {
        return out;
    }
    let lev = r.lev;
    let iz = 1.0 / x[2];
    let u = lev.fx * x[0] * iz + lev.cx;
    let v = lev.fy * x[1] * iz + lev.cy;
    // Nearest pixel (u, v >= -0.5 is checked before the cast truncates toward zero).
    if !(u > -0.5 && v > -0.5) {
        return out;
    }
    let (ui, vi) = ((u + 0.5) as usize, (v + 0.5) as usize);
    if ui >= lev.w || vi >= lev.h {
        return out;
    }
    let j = vi * lev.w + ui;
    out.pixel = j;
    let zr = r.igd[j][3];
    if zr <= 0.0 || (x[2] - zr).abs() > p.max_depth_diff {
        return out;
    }
    let n = r.normals[j];
    if n[3] > 0.0 {
        let vr = lev.point(ui, vi, zr);
        let nn = [n[0], n[1], n[2]];
        let rg = nn[0] * (x[0] - vr[0]) + nn[1] * (x[1] - vr[1]) + nn[2] * (x[2] - vr[2]);
        let c = cross(&x, &nn);
        out.geo = Some((rg, [nn[0], nn[1], nn[2], c[0], c[1], c[2]], x[2]));
    }
    if p.photo_weight > 0.0 && u >= 0.0 && v >= 0.0 {
        let (x0, y0) = (u as usize, v as usize);
        if x0 + 1 < lev.w && y0 + 1 < lev.h {
            let (ax, ay) = (u - x0 as f32, v - y0 as f32);
            let k = y0 * lev.w + x0;
            let (a, b, c, d) = (
                r.igd[k],
                r.igd[k + 1],
                r.igd[k + lev.w],
                r.igd[k + lev.w + 1],
            );
            let w00 = (1.0 - ax) * (1.0 - ay);
            let w10 = ax * (1.0 - ay);
            let w01 = (1.0 - ax) * ay;
            let w11 = ax * ay;
            let gx = w00 * a[1] + w10 * b[1] + w01 * c[1] + w11 * d[1];
            let gy = w00 * a[2] + w10 * b[2] + w01 * c[2] + w11 * d[2];
            if gx * gx + gy * gy >= p.min_grad_sq {
                let ir = w00 * a[0] + w10 * b[0] + w01 * c[0] + w11 * d[0];
                let rp = ir - p.gain * intensity_f;
                let gfx = gx * lev.fx * iz;
                let gfy = gy * lev.fy * iz;
                let g = [gfx, gfy, -(gfx * x[0] + gfy * x[1]) * iz];
                let c = cross(&x, &g);
                out.photo = Some((rp, [g[0], g[1], g[2], c[0], c[1], c[2]], ir));
            }
        }
    }
    out
}

/// Sums over the rows of chunk `c`, eight pixels at a time where `lanes` (AVX2 and FMA).
fn accumulate_chunk(
    r: &RefLevel<'_>,
    f: &Level,
    rot: &[[f32; 3]; 3],
    t: &[f32; 3],
    p: &Params,
    c: usize,
    lanes: bool,
) -> Sums {
    let mut s = Sums::default();
    let mut acc = RowAcc::default();
    let y1 = ((c + 1) * ROWS_PER_CHUNK).min(f.h);
    for y in c * ROWS_PER_CHUNK..y1 {
        // SAFETY: `lanes` only where the CPU has AVX2 and FMA (`accumulate`).
        #[cfg(target_arch = "x86_64")]
        let done = if lanes {
            unsafe { super::lanes::row_avx2(r, f, rot, t, p, y, &mut s) }
        } else {
            0
        };
        #[cfg(not(target_arch = "x86_64"))]
        let done = {
            let _ = lanes;
            0
        };
        let o = y * f.w;
        for x in done..f.w {
            let z = f.depth[o + x];
            if z <= 0.0 {
                continue;
            }
            s.n_valid += 1;
            let xf = f.point(x, y, z);
            let res = eval_point(r, &xf, f.intensity[o + x], rot, t, p);
            if let Some((rg, j, depth)) = res.geo {
                let s_n = (rg * p.inv_huber_g).abs();
                let (w, rho) = if s_n <= 1.0 {
                    (1.0, 0.5 * s_n * s_n)
                } else {
                    (1.0 / s_n, s_n - 0.5)
                };
                acc.add(&j, rg, w * p.inv_huber_g * p.inv_huber_g);
                acc.cost += rho;
                acc.depth_sum += depth;
                s.n_geo += 1;
                if rg.abs() <= p.inlier_threshold {
                    s.n_inlier += 1;
                    acc.sq_geo += rg * rg;
                }
            }
            if let Some((rp, j, ir)) = res.photo {
                let s_n = (rp * p.inv_huber_p).abs();
                let (w, rho) = if s_n <= 1.0 {
                    (1.0, 0.5 * s_n * s_n)
                } else {
                    (1.0 / s_n, s_n - 0.5)
                };
                acc.add(&j, rp, p.photo_weight * w * p.inv_huber_p * p.inv_huber_p);
                acc.cost += p.photo_weight * rho;
                acc.sq_photo += rp * rp;
                acc.sum_ir += ir;
                acc.sum_if += f.intensity[o + x];
                s.n_photo += 1;
            }
        }
        acc.flush(&mut s);
    }
    s
}

pub(crate) fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// One pass over the frame level: the normal equations at `T_rf = (rot, t)`.
///
/// Rows are split into fixed chunks, each summed sequentially, and the chunk sums are added
/// in order, so the result is bitwise identical for any number of threads (on a given CPU:
/// the AVX2 path, eight pixels at a time, sums in another order than the scalar one).
pub(crate) fn accumulate(
    r: &RefLevel<'_>,
    f: &Level,
    rot: &[[f32; 3]; 3],
    t: &[f32; 3],
    p: &Params,
) -> Sums {
    accumulate_with(r, f, rot, t, p, has_avx2_fma())
}

/// [`accumulate`], eight pixels at a time where `lanes` (the CPU must have AVX2 and FMA).
pub(crate) fn accumulate_with(
    r: &RefLevel<'_>,
    f: &Level,
    rot: &[[f32; 3]; 3],
    t: &[f32; 3],
    p: &Params,
    lanes: bool,
) -> Sums {
    let n_chunks = f.h.div_ceil(ROWS_PER_CHUNK);
    let parts: Vec<Sums> = (0..n_chunks)
        .into_par_iter()
        .map(|c| accumulate_chunk(r, f, rot, t, p, c, lanes))
        .collect();
    let mut total = Sums::default();
    for s in &parts {
        total.add(s);
    }
    total
}
