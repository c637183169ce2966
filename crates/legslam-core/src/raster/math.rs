//! Small fixed-size linear algebra in the engine's scalar type.

#[cfg(feature = "f64")]
pub use glam::{DMat3 as M3, DVec2 as V2, DVec3 as V3};
#[cfg(not(feature = "f64"))]
pub use glam::{Mat3 as M3, Vec2 as V2, Vec3 as V3};

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

/// Gradient of a loss with respect to (w, x, y, z), given its gradient `g` with respect to
/// the entries of `quat_to_mat(w, x, y, z)`.
#[inline]
pub fn quat_to_mat_vjp(w: Real, x: Real, y: Real, z: Real, g: &M3) -> [Real; 4] {
    let g = |i, j| at(g, i, j);
    [
        2.0 * (-z * g(0, 1) + y * g(0, 2) + z * g(1, 0) - x * g(1, 2) - y * g(2, 0) + x * g(2, 1)),
        2.0 * (y * g(0, 1) + z * g(0, 2) + y * g(1, 0) - 2.0 * x * g(1, 1) - w * g(1, 2)
            + z * g(2, 0)
            + w * g(2, 1)
            - 2.0 * x * g(2, 2)),
        2.0 * (-2.0 * y * g(0, 0) + x * g(0, 1) + w * g(0, 2) + x * g(1, 0) + z * g(1, 2)
            - w * g(2, 0)
            + z * g(2, 1)
            - 2.0 * y * g(2, 2)),
        2.0 * (-2.0 * z * g(0, 0) - w * g(0, 1) + x * g(0, 2) + w * g(1, 0) - 2.0 * z * g(1, 1)
            + y * g(1, 2)
            + x * g(2, 0)
            + y * g(2, 1)),
    ]
}

#[inline]
pub fn sigmoid(x: Real) -> Real {
    1.0 / (1.0 + (-x).exp())
}
