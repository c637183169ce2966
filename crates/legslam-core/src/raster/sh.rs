//! Real spherical harmonics up to degree 3 (the 3DGS basis and sign convention), with their
//! gradients with respect to the viewing direction.

// Full-precision constants serve the f64 build too.
#![allow(clippy::excessive_precision)]

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

/// Gradients of the basis functions with respect to the (unit) direction `d`.
#[inline]
pub fn basis_grad(degree: usize, d: V3, out: &mut [V3; 16]) {
    let (x, y, z) = (d.x, d.y, d.z);
    out[0] = V3::ZERO;
    if degree == 0 {
        return;
    }
    out[1] = V3::new(0.0, -C1, 0.0);
    out[2] = V3::new(0.0, 0.0, C1);
    out[3] = V3::new(-C1, 0.0, 0.0);
    if degree == 1 {
        return;
    }
    let (xx, yy, zz) = (x * x, y * y, z * z);
    out[4] = C2[0] * V3::new(y, x, 0.0);
    out[5] = C2[1] * V3::new(0.0, z, y);
    out[6] = C2[2] * V3::new(-2.0 * x, -2.0 * y, 4.0 * z);
    out[7] = C2[3] * V3::new(z, 0.0, x);
    out[8] = C2[4] * V3::new(2.0 * x, -2.0 * y, 0.0);
    if degree == 2 {
        return;
    }
    out[9] = C3[0] * V3::new(6.0 * x * y, 3.0 * xx - 3.0 * yy, 0.0);
    out[10] = C3[1] * V3::new(y * z, x * z, x * y);
    out[11] = C3[2] * V3::new(-2.0 * x * y, 4.0 * zz - xx - 3.0 * yy, 8.0 * y * z);
    out[12] = C3[3] * V3::new(-6.0 * x * z, -6.0 * y * z, 6.0 * zz - 3.0 * xx - 3.0 * yy);
    out[13] = C3[4] * V3::new(4.0 * zz - 3.0 * xx - yy, -2.0 * x * y, 8.0 * x * z);
    out[14] = C3[5] * V3::new(2.0 * x * z, -2.0 * y * z, xx - yy);
    out[15] = C3[6] * V3::new(3.0 * xx - 3.0 * yy, -6.0 * x * y, 0.0);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_gradient_matches_finite_differences() {
        let d = V3::new(0.3, -0.5, 0.8).normalize();
        let mut g = [V3::ZERO; 16];
        basis_grad(3, d, &mut g);
        let h = if cfg!(feature = "f64") { 1e-6 } else { 1e-3 };
        for axis in 0..3 {
            let mut e = V3::ZERO;
            e[axis] = h;
            let (mut bp, mut bm) = ([0.0; 16], [0.0; 16]);
            basis(3, d + e, &mut bp);
            basis(3, d - e, &mut bm);
            for k in 0..16 {
                let fd = (bp[k] - bm[k]) / (2.0 * h);
                assert!((fd - g[k][axis]).abs() < 1e-2, "k={k} axis={axis}");
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
