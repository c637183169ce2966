//! Small fixed-size linear algebra in the engine's scalar type.

#[cfg(feature = "f64")]
pub use glam::{DMat3 as M3, DVec2 as V2, DVec3 as V3};
#[cfg(not(feature = "f64"))]
pub use glam::{Mat3 as M3, Vec2 as V2, Vec3 as V3};

use super::lanes::Lanes;
use crate::Real;

/// A 3x3 matrix from its rows (glam stores columns).
#[inline]
pub fn mat3_rows(r0: V3, r1: V3, r2: V3) -> M3 {
    M3::from_cols(r0, r1, r2).transpose()
}

/// Entry (row i, column j).
#[inline]
pub fn at(m: &M3, i: usize, j: usize) -> Real {
    m.col(j)[i]
}

/// Rotation matrix of a unit quaternion (w, x, y, z).
#[inline]
pub fn quat_to_mat(w: Real, x: Real, y: Real, z: Real) -> M3 {
    mat3_rows(
        V3::new(
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ),
        V3::new(
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ),
        V3::new(
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ),
    )
}

#[inline]
pub fn sigmoid(x: Real) -> Real {
    1.0 / (1.0 + (-x).exp())
}

// Rounding to pixel and tile indices, eight Gaussians at a time (the projection's tile rects
// and pixel boxes), by truncation of the value clamped to [0, n]: x86-64 without SSE4.1 (the
// portable wheel's target) calls `floorf` and `ceilf` out of line. Each gives exactly what the
// float expression in its scalar version's comment gives (NaN and infinities included) for any
// `n` up to 2^24, where float integers are exact; the scalar versions, by integer conversion,
// are the plain references the tests below hold both to.

/// `v.floor().max(0.0).min(n as Real) as usize`.
#[cfg(test)]
pub fn floor_in(v: Real, n: usize) -> usize {
    // `as` truncates a non-negative value to its floor, and takes a negative one or NaN to 0.
    (v as usize).min(n)
}

/// `(v.floor() + 1.0).max(0.0).min(n as Real) as usize`: the end of a range whose last entry
/// is `floor(v)`.
#[cfg(test)]
pub fn floor_end_in(v: Real, n: usize) -> usize {
    if v >= 0.0 {
        (floor_in(v, n) + 1).min(n)
    } else {
        0
    }
}

/// `v.ceil().max(0.0).min(n as Real) as usize`.
#[cfg(test)]
pub fn ceil_in(v: Real, n: usize) -> usize {
    let t = v as usize;
    t.saturating_add(usize::from((t as Real) < v)).min(n)
}

/// [`floor_in`] of eight lanes (`n` up to 2^24), as integral floats.
#[inline(always)]
pub(crate) fn floor_in_lanes<L: Lanes>(v: L, n: Real) -> L {
    // maxps takes NaN to zero, as the integer conversion does.
    v.max(L::splat(0.0)).min(L::splat(n)).trunc()
}

/// [`floor_end_in`] of eight lanes.
#[inline(always)]
pub(crate) fn floor_end_in_lanes<L: Lanes>(v: L, n: Real) -> L {
    let zero = L::splat(0.0);
    let end = floor_in_lanes(v, n).add(L::splat(1.0)).min(L::splat(n));
    L::select(zero.le(v), end, zero)
}

/// [`ceil_in`] of eight lanes.
#[inline(always)]
pub(crate) fn ceil_in_lanes<L: Lanes>(v: L, n: Real) -> L {
    let c = v.max(L::splat(0.0)).min(L::splat(n));
    let t = c.trunc();
    L::select(t.lt(c), t.add(L::splat(1.0)), t)
}

#[cfg(test)]
mod tests {
    use super::super::lanes::{Portable, LANES};
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn integer_rounding_gives_the_float_expressions() {
        let mut rng = Rng::new(9);
        let mut values: Vec<Real> = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            -1.5,
            2.999_999,
            3.0,
            15.0,
            16.0,
            16.000_002,
            1e7,
            16_777_217.0,
            1e20,
            -1e20,
            Real::MAX,
            Real::MIN,
            Real::INFINITY,
            Real::NEG_INFINITY,
            Real::NAN,
            Real::MIN_POSITIVE,
        ];
        values.extend((0..20_000).map(|i| match i % 3 {
            0 => rng.uniform(-40.0, 700.0) as Real,
            1 => rng.uniform(-3.0, 3.0).round() as Real,
            _ => (rng.uniform(-8.0, 80.0) as Real / 16.0).round() * 16.0,
        }));
        for &v in &values {
            for n in [0, 1, 40, 640, 1 << 24] {
                let want = |x: Real| x.max(0.0).min(n as Real) as usize;
                assert_eq!(floor_in(v, n), want(v.floor()), "floor {v} in {n}");
                assert_eq!(
                    floor_end_in(v, n),
                    want(v.floor() + 1.0),
                    "floor + 1 {v} in {n}"
                );
                assert_eq!(ceil_in(v, n), want(v.ceil()), "ceil {v} in {n}");
            }
        }
        // The lane versions against the scalar ones, through the portable lanes (the vector
        // paths' `trunc` and `to_u32` against these in `lanes`' tests; the tile rects and
        // pixel boxes built on them in `project`'s).
        for chunk in values.chunks(LANES) {
            let mut v = [0.0; LANES];
            v[..chunk.len()].copy_from_slice(chunk);
            let lanes = Portable::load(&v);
            for n in [0, 1, 40, 640, 1 << 24] {
                let to = |x: Portable| x.to_u32().map(|i| i as usize);
                let each = |f: fn(Real, usize) -> usize| v.map(|x| f(x, n));
                let nf = n as Real;
                assert_eq!(to(floor_in_lanes(lanes, nf)), each(floor_in), "floor {v:?}");
                assert_eq!(
                    to(floor_end_in_lanes(lanes, nf)),
                    each(floor_end_in),
                    "end {v:?}"
                );
                assert_eq!(to(ceil_in_lanes(lanes, nf)), each(ceil_in), "ceil {v:?}");
            }
        }
    }
}
