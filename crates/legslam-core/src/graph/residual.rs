//! An edge's residual with its Jacobians, and the robust kernel of loop edges.

use nalgebra::{Matrix6, Vector6};

use crate::camera::{se3, Pose};

/// Residual `r = log(Z^-1 T_i^-1 T_j)` of an edge with measurement `Z` (passed as `z_inv`,
/// `Z^-1`) between camera-to-world poses `T_i` and `T_j`, with its Jacobians `(J_i, J_j)` for
/// the left perturbations `T <- exp(d) T` of each pose.
///
/// With `E = Z^-1 T_i^-1 T_j`, moving `T_j` gives `E exp(Ad(T_j^-1) d)` and moving `T_i` gives
/// `E exp(-Ad(T_j^-1) d)`, so `J_j = J_r^-1(r) Ad(T_j^-1)` and `J_i = -J_j`.
pub fn edge_residual(
    ti: &Pose,
    tj: &Pose,
    z_inv: &Pose,
) -> (Vector6<f64>, Matrix6<f64>, Matrix6<f64>) {
    let r = residual(ti, tj, z_inv);
    let jj = jacobian_to(&r, tj);
    (r, -jj, jj)
}

/// `J_j` of [`edge_residual`] from the residual `r` and `T_j`.
pub(crate) fn jacobian_to(r: &Vector6<f64>, tj: &Pose) -> Matrix6<f64> {
    se3::right_jacobian_inverse(r) * se3::adjoint(&se3::inverse(tj))
}

/// The residual of [`edge_residual`] alone.
pub(crate) fn residual(ti: &Pose, tj: &Pose, z_inv: &Pose) -> Vector6<f64> {
    se3::log(&(z_inv * se3::inverse(ti) * tj))
}

/// The Cauchy kernel on a squared Mahalanobis norm `chi2` with scale `c` (in the norm's units):
/// `(rho, w)` with `rho = c^2 ln(1 + chi2 / c^2)` the cost in place of `chi2`, and
/// `w = rho' = 1 / (1 + chi2 / c^2)` the weight of the edge's information in the normal
/// equations. `c = 0` means no kernel: `(chi2, 1)`.
pub(crate) fn cauchy(chi2: f64, c: f64) -> (f64, f64) {
    if c == 0.0 {
        return (chi2, 1.0);
    }
    let c2 = c * c;
    (c2 * (chi2 / c2).ln_1p(), 1.0 / (1.0 + chi2 / c2))
}
