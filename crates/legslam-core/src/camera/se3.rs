//! SE(3) algebra of [`super::Pose`]: exponential and logarithm, rigid inverse, and the checks
//! shared by the tracker, the mapper's pose refinement and the pose graph.
//!
//! **Twist convention.** A twist is `xi = (v, w)` in R^6, *translation first*:
//! `v = xi[0..3]` (metres), `w = xi[3..6]` (axis-angle, radians). Its hat is the 4x4 matrix
//! `[[w]x, v; 0, 0]` and `exp(xi)` the rigid transform it generates. The tracker perturbs
//! poses on the **left**: `T <- exp(delta) * T`, so a point `X` moves to `X + v + w x X` to
//! first order, and `d(exp(delta) X)/d(delta) = [I | -[X]x]` at `delta = 0`.
//!
//! The pose graph's Jacobians need two more pieces, in the same order: the [`adjoint`] (moves a
//! twist from one frame to another) and the inverse right Jacobian
//! ([`right_jacobian_inverse`]: how `log` changes under a small twist applied on the right).

use nalgebra::{Matrix3, Matrix4, Matrix6, Rotation3, Vector3, Vector6};

/// Skew-symmetric matrix `[w]x` with `[w]x a = w x a`.
pub fn hat3(w: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -w.z, w.y, w.z, 0.0, -w.x, -w.y, w.x, 0.0)
}

/// The left Jacobian `V` of SO(3) (so that `exp((v, w)).translation = V v`).
fn left_jacobian(w: &Vector3<f64>) -> Matrix3<f64> {
    let th2 = w.norm_squared();
    let th = th2.sqrt();
    let (b, c) = if th < 1e-4 {
        // Taylor series of (1-cos t)/t^2 and (t-sin t)/t^3.
        (0.5 - th2 / 24.0, 1.0 / 6.0 - th2 / 120.0)
    } else {
        ((1.0 - th.cos()) / th2, (th - th.sin()) / (th2 * th))
    };
    let k = hat3(w);
    Matrix3::identity() + k * b + k * k * c
}

/// Inverse of the SO(3) left Jacobian, in closed form (finite up to an angle of 2 pi).
fn left_jacobian_inverse(w: &Vector3<f64>) -> Matrix3<f64> {
    let th2 = w.norm_squared();
    let th = th2.sqrt();
    // 1/t^2 - (1 + cos t) / (2 t sin t), with (1 + cos t) / sin t = cot(t/2).
    let c = if th < 1e-4 {
        1.0 / 12.0 + th2 / 720.0
    } else {
        1.0 / th2 - 0.5 / (th * (0.5 * th).tan())
    };
    let k = hat3(w);
    Matrix3::identity() - k * 0.5 + k * k * c
}

/// The block `Q(rho, phi)` coupling translation and rotation in the SE(3) left Jacobian
/// `[[J(phi), Q], [0, J(phi)]]` (Barfoot, *State Estimation for Robotics*, eq. 7.86).
fn left_jacobian_q(rho: &Vector3<f64>, phi: &Vector3<f64>) -> Matrix3<f64> {
    let th2 = phi.norm_squared();
    let th = th2.sqrt();
    let (a, b, c) = if th < 0.1 {
        // Taylor series; the closed forms lose digits to cancellation at small angles.
        let th4 = th2 * th2;
        (
            1.0 / 6.0 - th2 / 120.0 + th4 / 5040.0,
            1.0 / 24.0 - th2 / 720.0 + th4 / 40320.0,
            1.0 / 120.0 - th2 / 2520.0 + th4 / 120960.0,
        )
    } else {
        let (s, co) = th.sin_cos();
        (
            (th - s) / (th2 * th),
            (th2 + 2.0 * co - 2.0) / (2.0 * th2 * th2),
            (2.0 * th - 3.0 * s + th * co) / (2.0 * th2 * th2 * th),
        )
    };
    let (r, p) = (hat3(rho), hat3(phi));
    let (pr, rp, prp) = (p * r, r * p, p * r * p);
    r * 0.5 + (pr + rp + prp) * a + (p * pr + rp * p - prp * 3.0) * b + (prp * p + p * prp) * c
}

/// The inverse right Jacobian of SE(3) at `xi`: `log(exp(xi) exp(d)) = xi +
/// right_jacobian_inverse(xi) d + O(|d|^2)`. Exact (not the `I + ad(xi)/2` approximation), so
/// Gauss-Newton keeps its quadratic convergence on large residuals.
pub fn right_jacobian_inverse(xi: &Vector6<f64>) -> Matrix6<f64> {
    // J_r(xi) = J_l(-xi), and [[J, Q], [0, J]]^-1 = [[J^-1, -J^-1 Q J^-1], [0, J^-1]].
    let rho = -Vector3::new(xi[0], xi[1], xi[2]);
    let phi = -Vector3::new(xi[3], xi[4], xi[5]);
    let j_inv = left_jacobian_inverse(&phi);
    let q = left_jacobian_q(&rho, &phi);
    let mut out = Matrix6::zeros();
    out.fixed_view_mut::<3, 3>(0, 0).copy_from(&j_inv);
    out.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(-(j_inv * q * j_inv)));
    out.fixed_view_mut::<3, 3>(3, 3).copy_from(&j_inv);
    out
}

/// The adjoint of `t`, `[[R, [p]x R], [0, R]]` for rotation `R` and translation `p`: it moves a
/// twist across `t`, `t exp(xi) t^-1 = exp(adjoint(t) xi)`.
pub fn adjoint(t: &Matrix4<f64>) -> Matrix6<f64> {
    let r = rotation(t);
    let mut a = Matrix6::zeros();
    a.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    a.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(hat3(&translation(t)) * r));
    a.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    a
}

/// `exp(xi)` as a 4x4 homogeneous transform (twist convention in the module docs).
pub fn exp(xi: &Vector6<f64>) -> Matrix4<f64> {
    let v = Vector3::new(xi[0], xi[1], xi[2]);
    let w = Vector3::new(xi[3], xi[4], xi[5]);
    let r = Rotation3::new(w).into_inner();
    let t = left_jacobian(&w) * v;
    from_rt(&r, &t)
}

/// `log(T)`, the inverse of [`exp`] for rotations of angle below pi.
pub fn log(t: &Matrix4<f64>) -> Vector6<f64> {
    let r = rotation(t);
    let w = so3_log(&r);
    let trans = translation(t);
    let v = left_jacobian(&w)
        .try_inverse()
        .unwrap_or_else(Matrix3::identity)
        * trans;
    Vector6::new(v.x, v.y, v.z, w.x, w.y, w.z)
}

/// Axis-angle vector of a rotation matrix, accurate for small angles.
fn so3_log(r: &Matrix3<f64>) -> Vector3<f64> {
    let vee = Vector3::new(
        r[(2, 1)] - r[(1, 2)],
        r[(0, 2)] - r[(2, 0)],
        r[(1, 0)] - r[(0, 1)],
    );
    let c = 0.5 * (r.trace() - 1.0);
    let s = 0.5 * vee.norm();
    if c < -0.99 {
        // Near pi the antisymmetric part vanishes; re-orthonormalise and let nalgebra find
        // the axis from the symmetric part.
        let rot = Rotation3::from_matrix_eps(r, 1e-15, 100, Rotation3::identity());
        return rot.scaled_axis();
    }
    let th = s.atan2(c);
    if s < 1e-12 {
        vee * 0.5
    } else {
        vee * (th / (2.0 * s))
    }
}

/// Rigid inverse of a homogeneous transform.
pub fn inverse(t: &Matrix4<f64>) -> Matrix4<f64> {
    let r = rotation(t);
    let rt = r.transpose();
    from_rt(&rt, &(-(rt * translation(t))))
}

/// `t` applied to the point `p` (a rigid transform: no homogeneous division).
pub fn transform_point(t: &Matrix4<f64>, p: &Vector3<f64>) -> Vector3<f64> {
    rotation(t) * p + translation(t)
}

/// The rotation block.
pub fn rotation(t: &Matrix4<f64>) -> Matrix3<f64> {
    t.fixed_view::<3, 3>(0, 0).into_owned()
}

/// The translation column.
pub fn translation(t: &Matrix4<f64>) -> Vector3<f64> {
    Vector3::new(t[(0, 3)], t[(1, 3)], t[(2, 3)])
}

/// Homogeneous transform from a rotation and a translation.
pub fn from_rt(r: &Matrix3<f64>, t: &Vector3<f64>) -> Matrix4<f64> {
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(r);
    m[(0, 3)] = t.x;
    m[(1, 3)] = t.y;
    m[(2, 3)] = t.z;
    m
}

/// Checks that `t` is a finite rigid transform (orthonormal rotation up to `tol`, last row
/// `0 0 0 1`).
pub fn validate_pose(t: &Matrix4<f64>, name: &str) -> Result<(), String> {
    if t.iter().any(|v| !v.is_finite()) {
        return Err(format!("{name} must be finite"));
    }
    let last = [t[(3, 0)], t[(3, 1)], t[(3, 2)], t[(3, 3)]];
    if (last[0].abs() + last[1].abs() + last[2].abs() + (last[3] - 1.0).abs()) > 1e-6 {
        return Err(format!(
            "{name} must have last row [0, 0, 0, 1], got {last:?}"
        ));
    }
    let r = rotation(t);
    let err = (r.transpose() * r - Matrix3::identity()).abs().max();
    if err > 1e-2 || r.determinant() < 0.0 {
        return Err(format!(
            "{name} rotation must be orthonormal with det +1 (max |R^T R - I| = {err:.2e})"
        ));
    }
    Ok(())
}

/// The nearest rigid transform (rotation block projected onto SO(3) by SVD), for poses read
/// at text precision.
pub fn orthonormalize(t: &Matrix4<f64>) -> Matrix4<f64> {
    let svd = rotation(t).svd(true, true);
    match (svd.u, svd.v_t) {
        (Some(u), Some(vt)) => {
            let mut r = u * vt;
            if r.determinant() < 0.0 {
                let mut u2 = u;
                u2.column_mut(2).neg_mut();
                r = u2 * vt;
            }
            from_rt(&r, &translation(t))
        }
        _ => *t,
    }
}

/// Rotation angle (radians) of a rigid transform.
pub fn rotation_angle(t: &Matrix4<f64>) -> f64 {
    let r = rotation(t);
    ((r.trace() - 1.0) * 0.5).clamp(-1.0, 1.0).acos()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn se3_exp_log_round_trip() {
        let cases = [
            Vector6::new(0.1, -0.2, 0.3, 0.01, 0.02, -0.03),
            Vector6::new(1.0, 2.0, -3.0, 1.0, -0.5, 2.0),
            Vector6::new(0.0, 0.0, 0.0, 1e-9, -2e-9, 1e-9),
            Vector6::new(0.5, 0.0, 0.1, 0.0, 3.0, 0.0),
            Vector6::zeros(),
        ];
        for xi in cases {
            let t = exp(&xi);
            let back = log(&t);
            assert!((back - xi).norm() < 1e-9, "{xi:?} -> {back:?}");
            let r = rotation(&t);
            assert!((r.transpose() * r - Matrix3::identity()).norm() < 1e-12);
            assert!((inverse(&t) * t - Matrix4::identity()).norm() < 1e-12);
            let p = Vector3::new(0.2, -0.7, 3.0);
            let q = transform_point(&inverse(&t), &transform_point(&t, &p));
            assert!((p - q).norm() < 1e-12);
        }
    }

    #[test]
    fn se3_exp_matches_series_and_left_perturbation() {
        // exp(xi) equals the matrix exponential of hat(xi) (power series).
        let xi = Vector6::new(0.3, -0.1, 0.2, 0.4, -0.3, 0.2);
        let mut hat = Matrix4::zeros();
        hat.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&hat3(&Vector3::new(xi[3], xi[4], xi[5])));
        hat[(0, 3)] = xi[0];
        hat[(1, 3)] = xi[1];
        hat[(2, 3)] = xi[2];
        let mut sum = Matrix4::identity();
        let mut term = Matrix4::identity();
        for k in 1..30 {
            term = term * hat / (k as f64);
            sum += term;
        }
        assert!((sum - exp(&xi)).norm() < 1e-12);
        // d(exp(d) X)/dd = [I | -[X]x] at d = 0.
        let x = Vector3::new(0.4, -1.2, 2.5);
        let h = 1e-6;
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let p = exp(&d) * x.push(1.0);
            d[k] = -h;
            let m = exp(&d) * x.push(1.0);
            let num = (p - m).xyz() / (2.0 * h);
            let mut ana = Vector3::zeros();
            if k < 3 {
                ana[k] = 1.0;
            } else {
                let mut e = Vector3::zeros();
                e[k - 3] = 1.0;
                ana = e.cross(&x);
            }
            assert!((num - ana).norm() < 1e-8, "column {k}: {num:?} vs {ana:?}");
        }
    }

    #[test]
    fn adjoint_moves_a_twist_across_a_transform() {
        let t = exp(&Vector6::new(1.5, -0.4, 2.0, 0.3, -1.1, 0.7));
        let xi = Vector6::new(0.02, -0.05, 0.01, 0.03, 0.01, -0.04);
        let lhs = t * exp(&xi) * inverse(&t);
        assert!((lhs - exp(&(adjoint(&t) * xi))).norm() < 1e-12);
    }

    #[test]
    fn right_jacobian_inverse_matches_central_differences() {
        // Small angles (the series branches), moderate and large ones (the closed forms).
        let cases = [
            Vector6::new(0.3, -0.2, 0.5, 1e-7, -2e-7, 1e-7),
            Vector6::new(0.3, -0.2, 0.5, 0.02, -0.05, 0.03),
            Vector6::new(1.0, 2.0, -0.5, 0.4, -0.3, 0.6),
            Vector6::new(-0.7, 0.1, 1.3, 1.2, 1.9, -0.8),
        ];
        let h = 1e-6;
        for xi in cases {
            let t = exp(&xi);
            let ana = right_jacobian_inverse(&xi);
            for k in 0..6 {
                let mut d = Vector6::zeros();
                d[k] = h;
                let plus = log(&(t * exp(&d)));
                let minus = log(&(t * exp(&(-d))));
                let num = (plus - minus) / (2.0 * h);
                let err = (num - ana.column(k)).norm();
                assert!(
                    err < 1e-7,
                    "xi {xi:?} column {k}: {num:?} vs {:?}",
                    ana.column(k)
                );
            }
        }
    }
}
