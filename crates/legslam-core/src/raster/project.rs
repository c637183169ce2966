//! Per-Gaussian projection (EWA splatting) and its backward pass.

// `!(x > 0.0)` is deliberate: it culls NaN as well.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use super::math::{at, quat_to_mat, quat_to_mat_vjp, sigmoid, M3, V2, V3};
use super::{sh, Camera, Gaussians, RasterConfig};
use crate::Real;

/// Pinhole parameters in the engine's scalar type, with the Jacobian's clamping limits.
#[derive(Clone, Copy)]
pub(crate) struct Pinhole {
    pub fx: Real,
    pub fy: Real,
    pub cx: Real,
    pub cy: Real,
    lim_x: (Real, Real),
    lim_y: (Real, Real),
}

impl Pinhole {
    pub fn new(cam: &Camera, cfg: &RasterConfig) -> Self {
        let k = &cam.intrinsics;
        let (fx, fy, cx, cy) = (k.fx as Real, k.fy as Real, k.cx as Real, k.cy as Real);
        let (w, h) = (k.width as Real, k.height as Real);
        let mx = cfg.fov_margin * 0.5 * w / fx;
        let my = cfg.fov_margin * 0.5 * h / fy;
        Pinhole {
            fx,
            fy,
            cx,
            cy,
            lim_x: (-(cx + 0.5) / fx - mx, (w - 0.5 - cx) / fx + mx),
            lim_y: (-(cy + 0.5) / fy - my, (h - 0.5 - cy) / fy + my),
        }
    }
}

/// Intermediate values of one Gaussian's projection, shared by forward and backward.
pub(crate) struct Geometry {
    pub p_cam: V3,
    /// Unnormalised quaternion norm and normalised quaternion (w, x, y, z).
    q_norm: Real,
    q: [Real; 4],
    rot: M3,
    scale: V3,
    cov_cam: M3,
    /// Rows of the 2x3 projection Jacobian, and whether x/z, y/z were clamped.
    j0: V3,
    j1: V3,
    clamped: (bool, bool),
    /// 2D covariance (with dilation) entries (xx, xy, yy) and its inverse, the conic (a, b, c).
    pub cov2d: V3,
    pub conic: V3,
    pub xy: V2,
}

/// Gaussian `i`'s centre in camera coordinates; `None` outside the near and far planes.
#[inline]
fn camera_point(g: &Gaussians, i: usize, cam: &Camera, cfg: &RasterConfig) -> Option<V3> {
    let m = &g.means[3 * i..3 * i + 3];
    let p = cam.rotation * V3::new(m[0], m[1], m[2]) + cam.translation;
    (p.z > cfg.near && p.z < cfg.far).then_some(p)
}

/// Projects Gaussian `i`; `None` when it is behind the near plane, beyond the far plane or
/// degenerate. Image-extent culling is the caller's.
#[inline]
pub(crate) fn geometry(
    g: &Gaussians,
    i: usize,
    cam: &Camera,
    pin: &Pinhole,
    cfg: &RasterConfig,
) -> Option<Geometry> {
    let p_cam = camera_point(g, i, cam, cfg)?;
    let z = p_cam.z;
    let qr = &g.quats[4 * i..4 * i + 4];
    let q_norm = (qr[0] * qr[0] + qr[1] * qr[1] + qr[2] * qr[2] + qr[3] * qr[3]).sqrt();
    if !(q_norm > 0.0) {
        return None;
    }
    let q = [
        qr[0] / q_norm,
        qr[1] / q_norm,
        qr[2] / q_norm,
        qr[3] / q_norm,
    ];
    let rot = quat_to_mat(q[0], q[1], q[2], q[3]);
    let ls = &g.log_scales[3 * i..3 * i + 3];
    let scale = V3::new(ls[0].exp(), ls[1].exp(), ls[2].exp());
    let mm = cam.rotation * rot * M3::from_diagonal(scale);
    let cov_cam = mm * mm.transpose();

    let (tx, ty) = (p_cam.x / z, p_cam.y / z);
    let sx = tx.clamp(pin.lim_x.0, pin.lim_x.1);
    let sy = ty.clamp(pin.lim_y.0, pin.lim_y.1);
    let j0 = V3::new(pin.fx / z, 0.0, -pin.fx * sx / z);
    let j1 = V3::new(0.0, pin.fy / z, -pin.fy * sy / z);
    let (cj0, cj1) = (cov_cam * j0, cov_cam * j1);
    let cov2d = V3::new(
        j0.dot(cj0) + cfg.dilation,
        j0.dot(cj1),
        j1.dot(cj1) + cfg.dilation,
    );
    let det = cov2d.x * cov2d.z - cov2d.y * cov2d.y;
    if !(det > 1e-12) {
        return None;
    }
    let conic = V3::new(cov2d.z / det, -cov2d.y / det, cov2d.x / det);
    let xy = V2::new(pin.fx * tx + pin.cx, pin.fy * ty + pin.cy);
    Some(Geometry {
        p_cam,
        q_norm,
        q,
        rot,
        scale,
        cov_cam,
        j0,
        j1,
        clamped: (sx != tx, sy != ty),
        cov2d,
        conic,
        xy,
    })
}

/// ln(opacity / alpha_min): the largest sigma (the exponent `0.5 d^T conic d`) at which a
/// Gaussian of this opacity still reaches the alpha cut-off.
#[inline]
pub(crate) fn cutoff_level(opacity: Real, cfg: &RasterConfig) -> Real {
    (opacity / cfg.alpha_min).ln()
}

/// The centre (pixels) and half extents that bound what [`geometry`] and [`extent`] would give
/// Gaussian `i` at `level` ([`cutoff_level`]), from its centre and largest scale alone
/// (`None` where `geometry` culls by depth): a cheap test that skips the full projection of
/// Gaussians that cannot reach the image. The Jacobian's rows have norm (f / z) sqrt(1 + s^2),
/// and the 3D covariance's largest eigenvalue is the largest scale squared.
#[inline]
pub(crate) fn extent_bound(
    g: &Gaussians,
    i: usize,
    cam: &Camera,
    pin: &Pinhole,
    level: Real,
    cfg: &RasterConfig,
) -> Option<(V2, V2)> {
    let p = camera_point(g, i, cam, cfg)?;
    let z = p.z;
    let ls = &g.log_scales[3 * i..3 * i + 3];
    let s2 = (2.0 * ls[0].max(ls[1]).max(ls[2])).exp();
    let (tx, ty) = (p.x / z, p.y / z);
    let sx = tx.clamp(pin.lim_x.0, pin.lim_x.1);
    let sy = ty.clamp(pin.lim_y.0, pin.lim_y.1);
    let level = level.max(0.0);
    // Slack well above rounding, so that the bound never falls below the exact extent.
    let half = |f: Real, s: Real| {
        let var = (f / z) * (f / z) * (1.0 + s * s) * s2 + cfg.dilation;
        (2.0 * level * var).sqrt() * 1.01 + 0.01
    };
    Some((
        V2::new(pin.fx * tx + pin.cx, pin.fy * ty + pin.cy),
        V2::new(half(pin.fx, sx), half(pin.fy, sy)),
    ))
}

/// Half extents (x, y) in pixels of the region where a Gaussian of 2D covariance `cov2d`
/// (xx, xy, yy) has alpha at least `alpha_min`: the bounding box of the ellipse
/// `0.5 d^T conic d <= level` ([`cutoff_level`]).
#[inline]
pub(crate) fn extent(cov2d: V3, level: Real) -> Option<V2> {
    if !(level > 0.0) {
        return None;
    }
    // Padded a hair so that rounding never drops a pixel whose alpha reaches the cut-off.
    let pad = |v: Real| v * 1.0001 + 1e-3;
    Some(V2::new(
        pad((2.0 * level * cov2d.x).sqrt()),
        pad((2.0 * level * cov2d.z).sqrt()),
    ))
}

/// The projected Gaussian `geo` in an image `s` times coarser (intrinsics scaled about pixel
/// centres, as an image pyramid's levels are): centre `(xy + 0.5) / s - 0.5`, covariance
/// `(cov2d - dilation) / s^2 + dilation` (the low-pass filter is one pixel of each image).
/// Returns centre, conic and covariance; `None` where the covariance degenerates.
#[inline]
pub(crate) fn coarser(geo: &Geometry, s: Real, cfg: &RasterConfig) -> Option<(V2, V3, V3)> {
    let (d, s2) = (cfg.dilation, s * s);
    let c = geo.cov2d;
    let cov2d = V3::new((c.x - d) / s2 + d, c.y / s2, (c.z - d) / s2 + d);
    let det = cov2d.x * cov2d.z - cov2d.y * cov2d.y;
    if !(det > 1e-12) {
        return None;
    }
    let conic = V3::new(cov2d.z / det, -cov2d.y / det, cov2d.x / det);
    Some(((geo.xy + 0.5) / s - 0.5, conic, cov2d))
}

/// d(loss)/d(2D covariance) as a 2x2 matrix, from d(loss)/d(conic entries a, b, c) (b counted
/// once, as it enters sigma): G_cov = -Q G_Q Q with G_Q the symmetric-matrix gradient.
#[inline]
pub(crate) fn conic_to_cov_grad(conic: V3, g_conic: V3) -> [[Real; 2]; 2] {
    let q2 = [[conic.x, conic.y], [conic.y, conic.z]];
    let gq = [[g_conic.x, 0.5 * g_conic.y], [0.5 * g_conic.y, g_conic.z]];
    let mut g_cov2 = [[0.0; 2]; 2];
    for (a, row) in g_cov2.iter_mut().enumerate() {
        for (b, v) in row.iter_mut().enumerate() {
            let mut sum = 0.0;
            for c in 0..2 {
                for d in 0..2 {
                    sum += q2[a][c] * gq[c][d] * q2[d][b];
                }
            }
            *v = -sum;
        }
    }
    g_cov2
}

/// View direction from the camera centre to the Gaussian, unnormalised.
#[inline]
fn view_dir(g: &Gaussians, i: usize, cam_pos: V3) -> V3 {
    let m = &g.means[3 * i..3 * i + 3];
    V3::new(m[0], m[1], m[2]) - cam_pos
}

/// SH colour (+0.5, before clamping at 0).
#[inline]
pub(crate) fn color_raw(g: &Gaussians, i: usize, degree: usize, cam_pos: V3) -> V3 {
    let n = sh::num_coeffs(degree);
    let coeffs = &g.sh[i * g.sh_coeffs * 3..];
    let mut b = [0.0; 16];
    if degree > 0 {
        sh::basis(degree, view_dir(g, i, cam_pos).normalize_or_zero(), &mut b);
    } else {
        b[0] = sh::basis_c0();
    }
    let mut c = V3::splat(0.5);
    for k in 0..n {
        c += b[k] * V3::new(coeffs[3 * k], coeffs[3 * k + 1], coeffs[3 * k + 2]);
    }
    c
}

/// Gradients of one Gaussian's screen-space quantities, gathered from all pixels.
#[derive(Clone, Copy, Default)]
pub(crate) struct ScreenGrads {
    pub xy: V2,
    /// With respect to the conic entries (a, b, c) as scalars.
    pub conic: V3,
    /// With respect to the 2D covariance as a matrix (xx, xy = yx, yy), beside what `conic`
    /// contributes (a coarser layer's share).
    pub cov: V3,
    pub opacity: Real,
    pub color: V3,
    pub depth: Real,
}

/// Where one Gaussian's parameter gradients go.
pub(crate) struct ParamGrads<'a> {
    pub mean: &'a mut [Real],
    pub log_scale: &'a mut [Real],
    pub quat: &'a mut [Real],
    pub opacity_logit: &'a mut Real,
    pub sh: &'a mut [Real],
}

/// Backward of the projection of Gaussian `i`: writes its parameter gradients and returns its
/// contribution to the pose gradient (rho, phi).
#[allow(clippy::too_many_arguments)]
pub(crate) fn backward_one(
    g: &Gaussians,
    i: usize,
    cam: &Camera,
    pin: &Pinhole,
    geo: &Geometry,
    sh_degree: usize,
    want_color: bool,
    sg: &ScreenGrads,
    out: ParamGrads,
) -> [Real; 6] {
    let z = geo.p_cam.z;
    let (x, y) = (geo.p_cam.x, geo.p_cam.y);
    let w_rot = cam.rotation;

    // Opacity.
    let o = sigmoid(g.opacity_logits[i]);
    *out.opacity_logit = sg.opacity * o * (1.0 - o);

    // Camera-space position: depth and the projected centre.
    let mut g_p = V3::new(0.0, 0.0, sg.depth);
    g_p.x += sg.xy.x * pin.fx / z;
    g_p.y += sg.xy.y * pin.fy / z;
    g_p.z -= (sg.xy.x * pin.fx * x + sg.xy.y * pin.fy * y) / (z * z);

    // Conic -> 2D covariance.
    let mut g_cov2 = conic_to_cov_grad(geo.conic, sg.conic);
    g_cov2[0][0] += sg.cov.x;
    g_cov2[0][1] += sg.cov.y;
    g_cov2[1][0] += sg.cov.y;
    g_cov2[1][1] += sg.cov.z;

    // 2D covariance = J cov_cam J^T: to cov_cam and to J.
    let (j0, j1) = (geo.j0, geo.j1);
    let outer = |a: V3, b: V3| M3::from_cols(a * b.x, a * b.y, a * b.z);
    let g_cov_cam = g_cov2[0][0] * outer(j0, j0)
        + g_cov2[0][1] * (outer(j0, j1) + outer(j1, j0))
        + g_cov2[1][1] * outer(j1, j1);
    let (cj0, cj1) = (geo.cov_cam * j0, geo.cov_cam * j1);
    let g_j0 = 2.0 * (g_cov2[0][0] * cj0 + g_cov2[0][1] * cj1);
    let g_j1 = 2.0 * (g_cov2[1][0] * cj0 + g_cov2[1][1] * cj1);

    // J -> camera-space position. J02 = -fx sx / z with sx = clamp(x / z).
    let sx = if geo.clamped.0 {
        -j0.z * z / pin.fx
    } else {
        x / z
    };
    let sy = if geo.clamped.1 {
        -j1.z * z / pin.fy
    } else {
        y / z
    };
    let (dsx_dx, dsx_dz) = if geo.clamped.0 {
        (0.0, 0.0)
    } else {
        (1.0 / z, -x / (z * z))
    };
    let (dsy_dy, dsy_dz) = if geo.clamped.1 {
        (0.0, 0.0)
    } else {
        (1.0 / z, -y / (z * z))
    };
    g_p.x += g_j0.z * (-pin.fx / z) * dsx_dx;
    g_p.y += g_j1.z * (-pin.fy / z) * dsy_dy;
    g_p.z += g_j0.x * (-pin.fx / (z * z))
        + g_j1.y * (-pin.fy / (z * z))
        + g_j0.z * (pin.fx * sx / (z * z) - pin.fx / z * dsx_dz)
        + g_j1.z * (pin.fy * sy / (z * z) - pin.fy / z * dsy_dz);

    // cov_cam = W cov_world W^T: to cov_world, and to the pose rotation.
    let g_cov_w = w_rot.transpose() * g_cov_cam * w_rot;
    let mrot = geo.cov_cam * g_cov_cam - g_cov_cam * geo.cov_cam;
    let mut g_phi = V3::new(
        at(&mrot, 1, 2) - at(&mrot, 2, 1),
        at(&mrot, 2, 0) - at(&mrot, 0, 2),
        at(&mrot, 0, 1) - at(&mrot, 1, 0),
    );

    // cov_world = M M^T, M = R S.
    let mm = geo.rot * M3::from_diagonal(geo.scale);
    let g_m = 2.0 * g_cov_w * mm;
    let mut g_rot_m = M3::ZERO;
    for j in 0..3 {
        let gc = g_m.col(j);
        let rc = geo.rot.col(j);
        out.log_scale[j] = gc.dot(rc) * geo.scale[j];
        *g_rot_m.col_mut(j) = gc * geo.scale[j];
    }
    let [w, qx, qy, qz] = geo.q;
    let g_qn = quat_to_mat_vjp(w, qx, qy, qz, &g_rot_m);
    let dot = g_qn[0] * w + g_qn[1] * qx + g_qn[2] * qy + g_qn[3] * qz;
    for (k, v) in out.quat.iter_mut().enumerate() {
        *v = (g_qn[k] - geo.q[k] * dot) / geo.q_norm;
    }

    // Colour: SH coefficients, and the view direction (to the mean and the camera centre).
    let mut g_mean = V3::ZERO;
    let mut g_rho = V3::ZERO;
    out.sh.fill(0.0);
    if want_color {
        let cam_pos = cam.position();
        let raw = color_raw(g, i, sh_degree, cam_pos);
        let gc = V3::new(
            if raw.x > 0.0 { sg.color.x } else { 0.0 },
            if raw.y > 0.0 { sg.color.y } else { 0.0 },
            if raw.z > 0.0 { sg.color.z } else { 0.0 },
        );
        let v = view_dir(g, i, cam_pos);
        let vn = v.length();
        let mut b = [0.0; 16];
        let mut db = [V3::ZERO; 16];
        if sh_degree > 0 && vn > 0.0 {
            sh::basis(sh_degree, v / vn, &mut b);
            sh::basis_grad(sh_degree, v / vn, &mut db);
        } else {
            b[0] = sh::basis_c0();
        }
        let coeffs = &g.sh[i * g.sh_coeffs * 3..];
        let mut g_dir = V3::ZERO;
        for k in 0..sh::num_coeffs(sh_degree) {
            out.sh[3 * k] = b[k] * gc.x;
            out.sh[3 * k + 1] = b[k] * gc.y;
            out.sh[3 * k + 2] = b[k] * gc.z;
            let c = V3::new(coeffs[3 * k], coeffs[3 * k + 1], coeffs[3 * k + 2]);
            g_dir += db[k] * c.dot(gc);
        }
        if sh_degree > 0 && vn > 0.0 {
            let d = v / vn;
            let g_v = (g_dir - d * d.dot(g_dir)) / vn;
            g_mean += g_v;
            g_rho += w_rot * g_v;
        }
    }

    // p_cam = W mean + t.
    g_mean += w_rot.transpose() * g_p;
    out.mean.copy_from_slice(&g_mean.to_array());
    g_rho += g_p;
    g_phi += geo.p_cam.cross(g_p);
    [g_rho.x, g_rho.y, g_rho.z, g_phi.x, g_phi.y, g_phi.z]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Intrinsics, Pose};
    use crate::rng::Rng;

    /// The cheap bound contains the exact extent of every Gaussian the full projection keeps,
    /// over random sizes, shapes, opacities, orientations and positions in and around the view
    /// (behind the camera, grazing the near plane, far off-axis).
    #[test]
    fn extent_bound_contains_the_exact_extent() {
        let mut rng = Rng::new(7);
        let n = 20_000;
        let mut means = Vec::new();
        let mut log_scales = Vec::new();
        let mut quats = Vec::new();
        let mut logits = Vec::new();
        for _ in 0..n {
            let z = rng.uniform(-0.5, 6.0);
            means.extend([rng.uniform(-4.0, 4.0), rng.uniform(-3.0, 3.0), z].map(|v| v as Real));
            log_scales.extend([0; 3].map(|_| rng.uniform(-7.0, 0.5) as Real));
            let q = [0; 4].map(|_| rng.normal());
            let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            quats.extend(q.map(|v| (v / norm) as Real));
            logits.push(rng.uniform(-8.0, 8.0) as Real);
        }
        let sh = vec![0.0; n * 3];
        let g = Gaussians {
            means: &means,
            log_scales: &log_scales,
            quats: &quats,
            opacity_logits: &logits,
            sh: &sh,
            sh_coeffs: 1,
            features: &[],
            num_features: 0,
        };
        let intr = Intrinsics::from_array([300.0, 310.0, 159.5, 119.5], 320, 240);
        let a = 0.3f64;
        #[rustfmt::skip]
        let w2c = Pose::new(
            a.cos(), 0.0, a.sin(), 0.1,
            0.0, 1.0, 0.0, -0.2,
            -a.sin(), 0.0, a.cos(), 0.3,
            0.0, 0.0, 0.0, 1.0,
        );
        let cam = Camera::new(intr, &w2c).unwrap();
        let cfg = RasterConfig::default();
        let pin = Pinhole::new(&cam, &cfg);
        let mut kept = 0;
        for (i, &logit) in logits.iter().enumerate() {
            let level = cutoff_level(sigmoid(logit), &cfg);
            let exact = geometry(&g, i, &cam, &pin, &cfg)
                .and_then(|geo| extent(geo.cov2d, level).map(|e| (geo.xy, e)));
            let Some((xy, e)) = exact else { continue };
            kept += 1;
            let (bxy, be) = extent_bound(&g, i, &cam, &pin, level, &cfg)
                .unwrap_or_else(|| panic!("Gaussian {i}: projected, but the bound culls it"));
            assert_eq!(bxy, xy, "Gaussian {i}: centre");
            for (lo_b, hi_b, lo, hi) in [
                (bxy.x - be.x, bxy.x + be.x, xy.x - e.x, xy.x + e.x),
                (bxy.y - be.y, bxy.y + be.y, xy.y - e.y, xy.y + e.y),
            ] {
                assert!(
                    lo_b <= lo && hi_b >= hi,
                    "Gaussian {i}: bound {be} < extent {e}"
                );
            }
        }
        assert!(kept > n / 4, "only {kept} of {n} Gaussians projected");
    }
}
