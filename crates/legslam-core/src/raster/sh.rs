//! Real spherical harmonics up to degree 3 (the 3DGS basis and sign convention), with their
//! gradients with respect to the viewing direction.

// Full-precision constants serve the f64 build too.
#![allow(clippy::excessive_precision)]

use super::lanes::Lanes;
use super::math::V3;
use crate::Real;

const C0: Real = 0.282_094_791_773_878_14;
const C1: Real = 0.488_602_511_902_919_9;
const C2: [Real; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
const C3: [Real; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// The degree-0 basis value (the constant).
pub const fn basis_c0() -> Real {
    C0
}

/// Number of coefficients per colour channel for a degree.
pub const fn num_coeffs(degree: usize) -> usize {
    (degree + 1) * (degree + 1)
}

/// The first `num_coeffs(degree)` basis functions at unit direction `d`.
#[inline]
pub fn basis(degree: usize, d: V3, out: &mut [Real; 16]) {
    let (x, y, z) = (d.x, d.y, d.z);
    out[0] = C0;
    if degree == 0 {
        return;
    }
    out[1] = -C1 * y;
    out[2] = C1 * z;
    out[3] = -C1 * x;
    if degree == 1 {
        return;
    }
    let (xx, yy, zz) = (x * x, y * y, z * z);
    out[4] = C2[0] * x * y;
    out[5] = C2[1] * y * z;
    out[6] = C2[2] * (2.0 * zz - xx - yy);
    out[7] = C2[3] * x * z;
    out[8] = C2[4] * (xx - yy);
    if degree == 2 {
        return;
    }
    out[9] = C3[0] * y * (3.0 * xx - yy);
    out[10] = C3[1] * x * y * z;
    out[11] = C3[2] * y * (4.0 * zz - xx - yy);
    out[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
    out[13] = C3[4] * x * (4.0 * zz - xx - yy);
    out[14] = C3[5] * z * (xx - yy);
    out[15] = C3[6] * x * (xx - 3.0 * yy);
}

/// [`basis`] of eight directions at once (lanes of x, y, z); entries past the degree's are
/// left as they are.
#[inline(always)]
pub(crate) fn basis_lanes<L: Lanes>(degree: usize, [x, y, z]: [L; 3], out: &mut [L; 16]) {
    let c = L::splat;
    out[0] = c(C0);
    if degree == 0 {
        return;
    }
    out[1] = c(-C1).mul(y);
    out[2] = c(C1).mul(z);
    out[3] = c(-C1).mul(x);
    if degree == 1 {
        return;
    }
    let (xx, yy, zz) = (x.mul(x), y.mul(y), z.mul(z));
    out[4] = c(C2[0]).mul(x).mul(y);
    out[5] = c(C2[1]).mul(y).mul(z);
    out[6] = c(C2[2]).mul(c(2.0).mul(zz).sub(xx).sub(yy));
    out[7] = c(C2[3]).mul(x).mul(z);
    out[8] = c(C2[4]).mul(xx.sub(yy));
    if degree == 2 {
        return;
    }
    out[9] = c(C3[0]).mul(y).mul(c(3.0).mul(xx).sub(yy));
    out[10] = c(C3[1]).mul(x).mul(y).mul(z);
    out[11] = c(C3[2]).mul(y).mul(c(4.0).mul(zz).sub(xx).sub(yy));
    out[12] = c(C3[3])
        .mul(z)
        .mul(c(2.0).mul(zz).sub(c(3.0).mul(xx)).sub(c(3.0).mul(yy)));
    out[13] = c(C3[4]).mul(x).mul(c(4.0).mul(zz).sub(xx).sub(yy));
    out[14] = c(C3[5]).mul(z).mul(xx.sub(yy));
    out[15] = c(C3[6]).mul(x).mul(xx.sub(c(3.0).mul(yy)));
}

/// `k v`. (A function, not a closure: a closure is compiled without the vector features of
/// the kernel it is called from, and its lane operations would not be inlined.)
#[inline(always)]
fn scaled<L: Lanes>(k: Real, v: [L; 3]) -> [L; 3] {
    let k = L::splat(k);
    [k.mul(v[0]), k.mul(v[1]), k.mul(v[2])]
}

/// [`basis_grad`] of eight directions at once: `out[k]` is basis function k's gradient (x, y,
/// z components). Entries past the degree's are left as they are.
#[inline(always)]
pub(crate) fn basis_grad_lanes<L: Lanes>(degree: usize, [x, y, z]: [L; 3], out: &mut [[L; 3]; 16]) {
    let c = L::splat;
    let zero = c(0.0);
    out[0] = [zero; 3];
    if degree == 0 {
        return;
    }
    out[1] = [zero, c(-C1), zero];
    out[2] = [zero, zero, c(C1)];
    out[3] = [c(-C1), zero, zero];
    if degree == 1 {
        return;
    }
    let (xx, yy, zz) = (x.mul(x), y.mul(y), z.mul(z));
    out[4] = scaled(C2[0], [y, x, zero]);
    out[5] = scaled(C2[1], [zero, z, y]);
    out[6] = scaled(C2[2], [c(-2.0).mul(x), c(-2.0).mul(y), c(4.0).mul(z)]);
    out[7] = scaled(C2[3], [z, zero, x]);
    out[8] = scaled(C2[4], [c(2.0).mul(x), c(-2.0).mul(y), zero]);
    if degree == 2 {
        return;
    }
    let (three, six) = (c(3.0), c(6.0));
    out[9] = scaled(
        C3[0],
        [six.mul(x).mul(y), three.mul(xx).sub(three.mul(yy)), zero],
    );
    out[10] = scaled(C3[1], [y.mul(z), x.mul(z), x.mul(y)]);
    out[11] = scaled(
        C3[2],
        [
            c(-2.0).mul(x).mul(y),
            c(4.0).mul(zz).sub(xx).sub(three.mul(yy)),
            c(8.0).mul(y).mul(z),
        ],
    );
    out[12] = scaled(
        C3[3],
        [
            c(-6.0).mul(x).mul(z),
            c(-6.0).mul(y).mul(z),
            six.mul(zz).sub(three.mul(xx)).sub(three.mul(yy)),
        ],
    );
    out[13] = scaled(
        C3[4],
        [
            c(4.0).mul(zz).sub(three.mul(xx)).sub(yy),
            c(-2.0).mul(x).mul(y),
            c(8.0).mul(x).mul(z),
        ],
    );
    out[14] = scaled(
        C3[5],
        [c(2.0).mul(x).mul(z), c(-2.0).mul(y).mul(z), xx.sub(yy)],
    );
    out[15] = scaled(
        C3[6],
        [
            three.mul(xx).sub(three.mul(yy)),
            c(-6.0).mul(x).mul(y),
            zero,
        ],
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::lanes::{Portable, LANES};

    fn lanes(d: V3) -> [Portable; 3] {
        [d.x, d.y, d.z].map(Portable::splat)
    }

    fn lane0(v: Portable) -> Real {
        let mut a = [0.0; LANES];
        v.store(&mut a);
        a[0]
    }

    /// The lane basis is the scalar one (which the reference renderer evaluates), at every
    /// degree; entries past a degree's are left alone.
    #[test]
    fn the_lane_basis_is_the_scalar_basis() {
        let d = V3::new(0.3, -0.5, 0.8).normalize();
        for degree in 0..=3 {
            let mut want = [0.0; 16];
            basis(degree, d, &mut want);
            let mut got = [Portable::splat(7.0); 16];
            basis_lanes(degree, lanes(d), &mut got);
            for k in 0..16 {
                let expected = if k < num_coeffs(degree) { want[k] } else { 7.0 };
                let tol = 1e-6 * expected.abs().max(1.0);
                assert!(
                    (lane0(got[k]) - expected).abs() <= tol,
                    "degree {degree}, k={k}"
                );
            }
        }
    }

    #[test]
    fn basis_gradient_matches_finite_differences() {
        let d = V3::new(0.3, -0.5, 0.8).normalize();
        let mut g = [[Portable::splat(0.0); 3]; 16];
        basis_grad_lanes(3, lanes(d), &mut g);
        let h = if cfg!(feature = "f64") { 1e-6 } else { 1e-3 };
        for axis in 0..3 {
            let mut e = V3::ZERO;
            e[axis] = h;
            let (mut bp, mut bm) = ([0.0; 16], [0.0; 16]);
            basis(3, d + e, &mut bp);
            basis(3, d - e, &mut bm);
            for k in 0..16 {
                let fd = (bp[k] - bm[k]) / (2.0 * h);
                let got = lane0(g[k][axis]);
                assert!((fd - got).abs() < 1e-2, "k={k} axis={axis}: {got} vs {fd}");
            }
        }
    }

    #[test]
    fn degree_zero_is_the_constant() {
        let mut b = [0.0; 16];
        basis(0, V3::Z, &mut b);
        assert!((b[0] - 1.0 / (2.0 * (std::f64::consts::PI as Real).sqrt())).abs() < 1e-6);
    }
}
