//! One row of [`super::solve::accumulate`] eight frame pixels at a time, with AVX2.
//!
//! Each lane evaluates the residuals of one pixel exactly as `eval_point` does (the same IEEE
//! operations in the same order, no fused multiply-add, so the residuals and the accepted
//! correspondences are the scalar ones); the reference samples are gathered. Only the sums
//! differ: each lane sums its own pixels of the row before the lanes are added, so the normal
//! equations match the scalar path's to rounding. The scalar path stays the fallback (other
//! CPUs, and the pixels of a row left over after its groups of eight) and the reference the
//! tests compare this one with.

use std::arch::x86_64::*;

use super::image::Level;
use super::solve::{Params, RefLevel, Sums};

/// Entries of a lane accumulator: the upper triangle of `J^T W J` (21), `J^T W r` (6), then
/// cost, squared geometric and photometric residuals, depth sum, reference and frame
/// intensity sums.
const H: usize = 0;
const B: usize = 21;
const COST: usize = 27;
const SQ_GEO: usize = 28;
const SQ_PHOTO: usize = 29;
const DEPTH: usize = 30;
const SUM_IR: usize = 31;
const SUM_IF: usize = 32;
const ENTRIES: usize = 33;

/// Per-lane sums of one row, and per-lane counts (n_valid, n_geo, n_photo, n_inlier).
struct LaneAcc {
    v: [__m256; ENTRIES],
    n: [__m256i; 4],
}

impl LaneAcc {
    #[inline(always)]
    unsafe fn new() -> LaneAcc {
        LaneAcc {
            v: [_mm256_setzero_ps(); ENTRIES],
            n: [_mm256_setzero_si256(); 4],
        }
    }

    /// Adds `w J J^T` and `w J r` of the lanes in `m` (the others may hold anything, even NaN).
    #[inline(always)]
    unsafe fn add(&mut self, j: &[__m256; 6], r: __m256, w: __m256, m: __m256) {
        // Written out rather than `j.map(..)`: a closure is compiled without this function's
        // target features and may be left as an outlined call in the hot loop.
        let mut j = *j;
        for v in &mut j {
            *v = _mm256_and_ps(*v, m);
        }
        let (r, w) = (_mm256_and_ps(r, m), _mm256_and_ps(w, m));
        let mut k = H;
        for a in 0..6 {
            let wa = _mm256_mul_ps(w, j[a]);
            for jb in &j[a..] {
                self.v[k] = _mm256_fmadd_ps(wa, *jb, self.v[k]);
                k += 1;
            }
            self.v[B + a] = _mm256_fmadd_ps(wa, r, self.v[B + a]);
        }
    }

    #[inline(always)]
    unsafe fn sum(&mut self, e: usize, x: __m256, m: __m256) {
        self.v[e] = _mm256_add_ps(self.v[e], _mm256_and_ps(x, m));
    }

    /// Counts the lanes in `m` (all bits set) in counter `c`.
    #[inline(always)]
    unsafe fn count(&mut self, c: usize, m: __m256) {
        self.n[c] = _mm256_sub_epi32(self.n[c], _mm256_castps_si256(m));
    }

    /// Adds the lanes into `s`, in f64.
    fn flush(&self, s: &mut Sums) {
        let lanes = |x: &__m256| -> f64 {
            // SAFETY: an __m256 is eight f32.
            let a: [f32; 8] = unsafe { std::mem::transmute(*x) };
            a.iter().map(|&v| v as f64).sum()
        };
        let counts = |x: &__m256i| -> u64 {
            // SAFETY: an __m256i is eight i32.
            let a: [i32; 8] = unsafe { std::mem::transmute(*x) };
            a.iter().map(|&v| v as u64).sum()
        };
        for (h, v) in s.h.iter_mut().zip(&self.v[H..B]) {
            *h += lanes(v);
        }
        for (b, v) in s.b.iter_mut().zip(&self.v[B..COST]) {
            *b += lanes(v);
        }
        s.cost += lanes(&self.v[COST]);
        s.sq_geo += lanes(&self.v[SQ_GEO]);
        s.sq_photo += lanes(&self.v[SQ_PHOTO]);
        s.depth_sum += lanes(&self.v[DEPTH]);
        s.sum_ir += lanes(&self.v[SUM_IR]);
        s.sum_if += lanes(&self.v[SUM_IF]);
        s.n_valid += counts(&self.n[0]);
        s.n_geo += counts(&self.n[1]);
        s.n_photo += counts(&self.n[2]);
        s.n_inlier += counts(&self.n[3]);
    }
}

#[inline(always)]
unsafe fn splat(v: f32) -> __m256 {
    _mm256_set1_ps(v)
}

#[inline(always)]
unsafe fn add(a: __m256, b: __m256) -> __m256 {
    _mm256_add_ps(a, b)
}

#[inline(always)]
unsafe fn sub(a: __m256, b: __m256) -> __m256 {
    _mm256_sub_ps(a, b)
}

#[inline(always)]
unsafe fn mul(a: __m256, b: __m256) -> __m256 {
    _mm256_mul_ps(a, b)
}

#[inline(always)]
unsafe fn and(a: __m256, b: __m256) -> __m256 {
    _mm256_and_ps(a, b)
}

#[inline(always)]
unsafe fn gt(a: __m256, b: __m256) -> __m256 {
    _mm256_cmp_ps::<_CMP_GT_OQ>(a, b)
}

#[inline(always)]
unsafe fn ge(a: __m256, b: __m256) -> __m256 {
    _mm256_cmp_ps::<_CMP_GE_OQ>(a, b)
}

#[inline(always)]
unsafe fn le(a: __m256, b: __m256) -> __m256 {
    _mm256_cmp_ps::<_CMP_LE_OQ>(a, b)
}

#[inline(always)]
unsafe fn lt(a: __m256, b: __m256) -> __m256 {
    _mm256_cmp_ps::<_CMP_LT_OQ>(a, b)
}

#[inline(always)]
unsafe fn abs(a: __m256) -> __m256 {
    _mm256_andnot_ps(splat(-0.0), a)
}

/// `a x b`, as `cross` in solve.rs.
#[inline(always)]
unsafe fn cross(a: &[__m256; 3], b: &[__m256; 3]) -> [__m256; 3] {
    [
        sub(mul(a[1], b[2]), mul(a[2], b[1])),
        sub(mul(a[2], b[0]), mul(a[0], b[2])),
        sub(mul(a[0], b[1]), mul(a[1], b[0])),
    ]
}

/// `base[idx]` in the lanes of `m`, 0 elsewhere.
#[inline(always)]
unsafe fn gather(base: *const f32, idx: __m256i, m: __m256) -> __m256 {
    _mm256_mask_i32gather_ps::<4>(_mm256_setzero_ps(), base, idx, m)
}

/// The Huber weight and cost of normalised residuals `s` (>= 0), as in solve.rs.
#[inline(always)]
unsafe fn huber(s: __m256) -> (__m256, __m256) {
    let inside = le(s, splat(1.0));
    let w = _mm256_blendv_ps(_mm256_div_ps(splat(1.0), s), splat(1.0), inside);
    let rho = _mm256_blendv_ps(sub(s, splat(0.5)), mul(mul(splat(0.5), s), s), inside);
    (w, rho)
}

/// Adds the pixels of frame row `y` in groups of eight to `s`; returns how many it took (the
/// rest of the row is the caller's).
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn row_avx2(
    r: &RefLevel<'_>,
    f: &Level,
    rot: &[[f32; 3]; 3],
    t: &[f32; 3],
    p: &Params,
    y: usize,
    s: &mut Sums,
) -> usize {
    let lev = r.lev;
    let groups = f.w / 8;
    // Indices are i32 (the gathers'): a level of up to 2^29 pixels.
    if groups == 0 || lev.w * lev.h * 4 >= i32::MAX as usize {
        return 0;
    }
    let mut acc = LaneAcc::new();
    let igd = r.igd.as_ptr() as *const f32;
    let normals = r.normals.as_ptr() as *const f32;
    let (rw, rh) = (lev.w as f32, lev.h as f32);
    let wi = _mm256_set1_epi32(lev.w as i32);
    let (fx, fy, cx, cy) = (splat(lev.fx), splat(lev.fy), splat(lev.cx), splat(lev.cy));
    let zero = _mm256_setzero_ps();
    // Plain loops, not closures (see `LaneAcc::add`).
    let mut rs = [[zero; 3]; 3];
    let mut ts = [zero; 3];
    for i in 0..3 {
        for k in 0..3 {
            rs[i][k] = splat(rot[i][k]);
        }
        ts[i] = splat(t[i]);
    }
    let yr = splat(f.yr[y]);
    let o = y * f.w;
    for g in 0..groups {
        let x0 = 8 * g;
        let z = _mm256_loadu_ps(f.depth.as_ptr().add(o + x0));
        let valid = gt(z, zero);
        if _mm256_movemask_ps(valid) == 0 {
            continue;
        }
        acc.count(0, valid);
        let xf = [
            mul(_mm256_loadu_ps(f.xr.as_ptr().add(x0)), z),
            mul(yr, z),
            z,
        ];
        let mut xc = [zero; 3];
        for i in 0..3 {
            xc[i] = add(
                add(
                    add(mul(rs[i][0], xf[0]), mul(rs[i][1], xf[1])),
                    mul(rs[i][2], xf[2]),
                ),
                ts[i],
            );
        }
        let mut m = and(valid, gt(xc[2], splat(1e-3)));
        let iz = _mm256_div_ps(splat(1.0), xc[2]);
        let u = add(mul(mul(fx, xc[0]), iz), cx);
        let v = add(mul(mul(fy, xc[1]), iz), cy);
        // Nearest pixel: u + 0.5 in [0, w) (as `(u + 0.5) as usize < w`).
        let (uh, vh) = (add(u, splat(0.5)), add(v, splat(0.5)));
        m = and(m, and(gt(u, splat(-0.5)), gt(v, splat(-0.5))));
        m = and(m, and(lt(uh, splat(rw)), lt(vh, splat(rh))));
        if _mm256_movemask_ps(m) == 0 {
            continue;
        }
        let mi = _mm256_castps_si256(m);
        let ui = _mm256_and_si256(_mm256_cvttps_epi32(uh), mi);
        let vi = _mm256_and_si256(_mm256_cvttps_epi32(vh), mi);
        let j4 = _mm256_slli_epi32::<2>(_mm256_add_epi32(_mm256_mullo_epi32(vi, wi), ui));
        let zr = gather(igd.add(3), j4, m);
        m = and(
            m,
            and(
                gt(zr, zero),
                le(abs(sub(xc[2], zr)), splat(p.max_depth_diff)),
            ),
        );
        if _mm256_movemask_ps(m) == 0 {
            continue;
        }

        // Point to plane.
        let nw = gather(normals.add(3), j4, m);
        let gm = and(m, gt(nw, zero));
        if _mm256_movemask_ps(gm) != 0 {
            let n = [
                gather(normals, j4, gm),
                gather(normals.add(1), j4, gm),
                gather(normals.add(2), j4, gm),
            ];
            let vr = [
                mul(gather(lev.xr.as_ptr(), ui, gm), zr),
                mul(gather(lev.yr.as_ptr(), vi, gm), zr),
                zr,
            ];
            let rg = add(
                add(mul(n[0], sub(xc[0], vr[0])), mul(n[1], sub(xc[1], vr[1]))),
                mul(n[2], sub(xc[2], vr[2])),
            );
            let c = cross(&xc, &n);
            let ih = splat(p.inv_huber_g);
            let (w, rho) = huber(abs(mul(rg, ih)));
            let w = mul(mul(w, ih), ih);
            acc.add(&[n[0], n[1], n[2], c[0], c[1], c[2]], rg, w, gm);
            acc.sum(COST, rho, gm);
            acc.sum(DEPTH, xc[2], gm);
            acc.count(1, gm);
            let inlier = and(gm, le(abs(rg), splat(p.inlier_threshold)));
            acc.count(3, inlier);
            acc.sum(SQ_GEO, mul(rg, rg), inlier);
        }

        // Photometric, bilinear at (u, v): x0 + 1 < w and y0 + 1 < h.
        if p.photo_weight > 0.0 {
            let pm = and(
                m,
                and(
                    and(ge(u, zero), ge(v, zero)),
                    and(lt(u, splat(rw - 1.0)), lt(v, splat(rh - 1.0))),
                ),
            );
            if _mm256_movemask_ps(pm) == 0 {
                continue;
            }
            let pi = _mm256_castps_si256(pm);
            let xi = _mm256_and_si256(_mm256_cvttps_epi32(u), pi);
            let yi = _mm256_and_si256(_mm256_cvttps_epi32(v), pi);
            let ax = sub(u, _mm256_cvtepi32_ps(xi));
            let ay = sub(v, _mm256_cvtepi32_ps(yi));
            let k4 = _mm256_slli_epi32::<2>(_mm256_add_epi32(_mm256_mullo_epi32(yi, wi), xi));
            let corner = |dk: i32, ch: usize| {
                gather(
                    igd.add(ch),
                    _mm256_add_epi32(k4, _mm256_set1_epi32(4 * dk)),
                    pm,
                )
            };
            let one = splat(1.0);
            let w00 = mul(sub(one, ax), sub(one, ay));
            let w10 = mul(ax, sub(one, ay));
            let w01 = mul(sub(one, ax), ay);
            let w11 = mul(ax, ay);
            let stride = lev.w as i32;
            let interp = |ch: usize| {
                add(
                    add(
                        add(mul(w00, corner(0, ch)), mul(w10, corner(1, ch))),
                        mul(w01, corner(stride, ch)),
                    ),
                    mul(w11, corner(stride + 1, ch)),
                )
            };
            let (gx, gy) = (interp(1), interp(2));
            let pm = and(pm, ge(add(mul(gx, gx), mul(gy, gy)), splat(p.min_grad_sq)));
            if _mm256_movemask_ps(pm) == 0 {
                continue;
            }
            let ir = interp(0);
            let i_f = _mm256_loadu_ps(f.intensity.as_ptr().add(o + x0));
            let rp = sub(ir, mul(splat(p.gain), i_f));
            let gfx = mul(mul(gx, fx), iz);
            let gfy = mul(mul(gy, fy), iz);
            let gz = mul(
                _mm256_xor_ps(add(mul(gfx, xc[0]), mul(gfy, xc[1])), splat(-0.0)),
                iz,
            );
            let g = [gfx, gfy, gz];
            let c = cross(&xc, &g);
            let ih = splat(p.inv_huber_p);
            let pw = splat(p.photo_weight);
            let (w, rho) = huber(abs(mul(rp, ih)));
            let w = mul(mul(mul(pw, w), ih), ih);
            acc.add(&[g[0], g[1], g[2], c[0], c[1], c[2]], rp, w, pm);
            acc.sum(COST, mul(pw, rho), pm);
            acc.sum(SQ_PHOTO, mul(rp, rp), pm);
            acc.sum(SUM_IR, ir, pm);
            acc.sum(SUM_IF, i_f, pm);
            acc.count(2, pm);
        }
    }
    acc.flush(s);
    8 * groups
}
