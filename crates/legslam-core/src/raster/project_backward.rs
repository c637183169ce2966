//! The projection's backward pass eight Gaussians at a time, over [`Lanes`]: from each
//! Gaussian's screen-space gradients (the sums over its tiles' pairs) to the gradients of its
//! parameters and its share of the camera pose's. The forward quantities come from the forward
//! pass's own functions ([`centre`], [`shape`], [`colour`]), so they are its values, bit for bit.

use super::lanes::{dispatch, Lanes, Simd, LANES};
use super::math::{V2, V3};
use super::project::{centre, colour, dot3, lanes, shape, Rows, View, WIDEST_ROW};
use super::sh;
use crate::Real;

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

/// Where a block's parameter gradients go: the block's rows of each array.
pub(crate) struct BlockGrads<'a> {
    pub mean: &'a mut [Real],
    pub log_scale: &'a mut [Real],
    pub quat: &'a mut [Real],
    pub opacity_logit: &'a mut [Real],
    pub sh: &'a mut [Real],
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

/// The parameter gradients of a task's Gaussians `first..first + screen.len()` that are `on`
/// screen, from their screen-space gradients, into `out` (the task's rows), through the
/// implementation `simd` chose; returns their share of the pose gradient, summed in order.
pub(crate) fn backward_task(
    simd: Simd,
    v: &View,
    first: usize,
    screen: &[ScreenGrads],
    on: &[bool],
    out: BlockGrads,
) -> [Real; 6] {
    dispatch!(
        simd,
        blocks(
            v: &View,
            first: usize,
            screen: &[ScreenGrads],
            on: &[bool],
            out: BlockGrads,
        ) -> [Real; 6]
    )
}

#[inline(always)]
fn blocks<L: Lanes>(
    v: &View,
    first: usize,
    screen: &[ScreenGrads],
    on: &[bool],
    out: BlockGrads,
) -> [Real; 6] {
    let nc = v.g.sh_coeffs * 3;
    let mut pose = [0.0; 6];
    for b in (0..screen.len()).step_by(LANES) {
        let count = (screen.len() - b).min(LANES);
        let bits = on[b..b + count]
            .iter()
            .enumerate()
            .fold(0u32, |m, (l, &o)| m | (u32::from(o) << l));
        if bits == 0 {
            continue;
        }
        let mut lanes_in = [ScreenGrads::default(); LANES];
        lanes_in[..count].copy_from_slice(&screen[b..b + count]);
        let rows = Rows {
            first: first + b,
            n: v.g.len(),
        };
        let block = BlockGrads {
            mean: &mut out.mean[3 * b..3 * (b + count)],
            log_scale: &mut out.log_scale[3 * b..3 * (b + count)],
            quat: &mut out.quat[4 * b..4 * (b + count)],
            opacity_logit: &mut out.opacity_logit[b..b + count],
            sh: &mut out.sh[nc * b..nc * (b + count)],
        };
        backward_block::<L>(v, &rows, count, bits, &lanes_in, block, &mut pose);
    }
    pose
}

/// Eight values as lanes.
#[inline(always)]
fn load<L: Lanes>(v: [Real; LANES]) -> L {
    L::load(&v)
}

/// Entry (i, j) of a symmetric 3x3 matrix stored as 00, 01, 02, 11, 12, 22.
#[inline(always)]
fn sym<L: Lanes>(m: &[L; 6], i: usize, j: usize) -> L {
    const AT: [[usize; 3]; 3] = [[0, 1, 2], [1, 3, 4], [2, 4, 5]];
    m[AT[i][j]]
}

/// Row i of (symmetric `a`) times (symmetric `b`), entry j.
#[inline(always)]
fn sym_product<L: Lanes>(a: &[L; 6], b: &[L; 6], i: usize, j: usize) -> L {
    sym(a, i, 0)
        .mul(sym(b, 0, j))
        .add(sym(a, i, 1).mul(sym(b, 1, j)))
        .add(sym(a, i, 2).mul(sym(b, 2, j)))
}

// The matrix helpers are functions, not closures: a closure is compiled without the vector
// features of the kernel that calls it, and its lane operations would not be inlined.

/// A matrix of scalars (rows), splatted.
#[inline(always)]
fn splat33<L: Lanes>(m: &[[Real; 3]; 3]) -> [[L; 3]; 3] {
    let mut out = [[L::splat(0.0); 3]; 3];
    for (o, r) in out.iter_mut().zip(m) {
        *o = [L::splat(r[0]), L::splat(r[1]), L::splat(r[2])];
    }
    out
}

/// W^T G W for symmetric G: its entries 00, 01, 02, 11, 12, 22.
#[inline(always)]
fn congruence<L: Lanes>(w: &[[L; 3]; 3], g: &[L; 6]) -> [L; 6] {
    // T = G W, then (W^T T)_ij = W's column i . T's column j.
    let mut t = [[L::splat(0.0); 3]; 3];
    for (i, row) in t.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = dot3(
                [sym(g, i, 0), sym(g, i, 1), sym(g, i, 2)],
                [w[0][j], w[1][j], w[2][j]],
            );
        }
    }
    let at = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];
    let mut out = [L::splat(0.0); 6];
    for (o, (i, j)) in out.iter_mut().zip(at) {
        *o = dot3([w[0][i], w[1][i], w[2][i]], [t[0][j], t[1][j], t[2][j]]);
    }
    out
}

/// 2 G M for symmetric G and M = R S, whose column j is R's column j (`rot_cols[j]`) times s_j.
#[inline(always)]
fn twice_sym_times_m<L: Lanes>(g: &[L; 6], rot_cols: &[[L; 3]; 3], scale: &[L; 3]) -> [[L; 3]; 3] {
    let two = L::splat(2.0);
    let mut out = [[L::splat(0.0); 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            let gi = [sym(g, i, 0), sym(g, i, 1), sym(g, i, 2)];
            *v = two.mul(dot3(gi, rot_cols[j]).mul(scale[j]));
        }
    }
    out
}

/// The gradient with respect to the quaternion (w, x, y, z) of the rotation matrix it makes
/// (as [`super::math::quat_to_mat`]), from the gradient `gr` with respect to that matrix's
/// entries (rows).
#[inline(always)]
fn quat_vjp<L: Lanes>(q: [L; 4], gr: &[[L; 3]; 3]) -> [L; 4] {
    let [w, x, y, z] = q;
    // The off-diagonal entries' sums and differences, and the diagonal.
    let (s01, s02, s12) = (
        gr[0][1].add(gr[1][0]),
        gr[0][2].add(gr[2][0]),
        gr[1][2].add(gr[2][1]),
    );
    let (a10, a02, a21) = (
        gr[1][0].sub(gr[0][1]),
        gr[0][2].sub(gr[2][0]),
        gr[2][1].sub(gr[1][2]),
    );
    let (g00, g11, g22) = (gr[0][0], gr[1][1], gr[2][2]);
    let two = L::splat(2.0);
    [
        two.mul(a10.mul(z).add(a02.mul(y)).add(a21.mul(x))),
        vector_part(s01, y, s02, z, a21, w, x, g11.add(g22)),
        vector_part(s01, x, s12, z, a02, w, y, g00.add(g22)),
        vector_part(s02, x, s12, y, a10, w, z, g00.add(g11)),
    ]
}

/// A vector component v of [`quat_vjp`]: 2 (sa a + sb b + anti w - 2 v diagonal).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn vector_part<L: Lanes>(sa: L, a: L, sb: L, b: L, anti: L, w: L, v: L, diagonal: L) -> L {
    let two = L::splat(2.0);
    let linear = sa.mul(a).add(sb.mul(b)).add(anti.mul(w));
    two.mul(linear.sub(two.mul(v).mul(diagonal)))
}

/// `m` with column j times `scale[j]`.
#[inline(always)]
fn scale_columns<L: Lanes>(m: &[[L; 3]; 3], scale: &[L; 3]) -> [[L; 3]; 3] {
    let mut out = *m;
    for row in out.iter_mut() {
        for (v, s) in row.iter_mut().zip(scale) {
            *v = v.mul(*s);
        }
    }
    out
}

/// The gradients of the block `rows` of Gaussians whose bit is set in `on` (the first
/// `count` lanes at most), from their screen-space gradients `screen`, into `out`'s rows (the
/// other rows are left as they are); adds their shares of the pose gradient (rho, phi) to
/// `pose`, lane by lane.
#[inline(always)]
pub(crate) fn backward_block<L: Lanes>(
    v: &View,
    rows: &Rows,
    count: usize,
    on: u32,
    screen: &[ScreenGrads; LANES],
    out: BlockGrads,
    pose: &mut [Real; 6],
) {
    let c = L::splat;
    let (zero, one, two) = (c(0.0), c(1.0), c(2.0));
    let ce = centre::<L>(v, rows);
    let sh = shape(v, rows, &ce);
    let pin = &v.pin;
    let (fx, fy) = (c(pin.fx), c(pin.fy));
    let [x, y, z] = ce.p_cam;
    let z2 = z.mul(z);
    let s = |f: fn(&ScreenGrads) -> Real| std::array::from_fn(|l| f(&screen[l]));
    let (sg_x, sg_y): (L, L) = (load(s(|g| g.xy.x)), load(s(|g| g.xy.y)));
    let sg_conic: [L; 3] = [
        load(s(|g| g.conic.x)),
        load(s(|g| g.conic.y)),
        load(s(|g| g.conic.z)),
    ];
    let sg_cov: [L; 3] = [
        load(s(|g| g.cov.x)),
        load(s(|g| g.cov.y)),
        load(s(|g| g.cov.z)),
    ];
    let sg_opacity: L = load(s(|g| g.opacity));
    let sg_depth: L = load(s(|g| g.depth));

    // Opacity, through the sigmoid.
    let o = ce.opacity;
    let g_logit = sg_opacity.mul(o).mul(one.sub(o));

    // The camera-space position: the depth and the projected centre.
    let mut g_p = [
        sg_x.mul(fx).div(z),
        sg_y.mul(fy).div(z),
        sg_depth.sub(sg_x.mul(fx).mul(x).add(sg_y.mul(fy).mul(y)).div(z2)),
    ];

    // Conic -> 2D covariance: G = -Q G_Q Q with G_Q the symmetric-matrix gradient (b counted
    // once as it enters sigma), plus the coarse layer's share, given for the covariance.
    let [a, b, cc] = sh.conic;
    let half_b = c(0.5).mul(sg_conic[1]);
    let (qg00, qg01) = (
        a.mul(sg_conic[0]).add(b.mul(half_b)),
        a.mul(half_b).add(b.mul(sg_conic[2])),
    );
    let (qg10, qg11) = (
        b.mul(sg_conic[0]).add(cc.mul(half_b)),
        b.mul(half_b).add(cc.mul(sg_conic[2])),
    );
    let g00 = sg_cov[0].sub(qg00.mul(a).add(qg01.mul(b)));
    let g01 = sg_cov[1].sub(qg00.mul(b).add(qg01.mul(cc)));
    let g11 = sg_cov[2].sub(qg10.mul(b).add(qg11.mul(cc)));

    // The 2D covariance J C J^T: to the camera-space covariance C, and to J, whose rows are
    // (j0x, 0, j0z) and (0, j1y, j1z).
    let [j0x, j0z, j1y, j1z] = sh.j;
    let g_cc: [L; 6] = [
        g00.mul(j0x).mul(j0x),
        g01.mul(j0x).mul(j1y),
        g00.mul(j0x).mul(j0z).add(g01.mul(j0x).mul(j1z)),
        g11.mul(j1y).mul(j1y),
        g01.mul(j0z).mul(j1y).add(g11.mul(j1y).mul(j1z)),
        g00.mul(j0z)
            .mul(j0z)
            .add(two.mul(g01).mul(j0z).mul(j1z))
            .add(g11.mul(j1z).mul(j1z)),
    ];
    let g_j0 = [
        two.mul(g00.mul(sh.cj0[0]).add(g01.mul(sh.cj1[0]))),
        two.mul(g00.mul(sh.cj0[2]).add(g01.mul(sh.cj1[2]))),
    ];
    let g_j1 = [
        two.mul(g01.mul(sh.cj0[1]).add(g11.mul(sh.cj1[1]))),
        two.mul(g01.mul(sh.cj0[2]).add(g11.mul(sh.cj1[2]))),
    ];

    // J -> the camera-space position: J02 = -fx sx / z with sx = x / z where not clamped.
    let [sx, sy] = ce.clamped;
    let [tx, ty] = ce.t;
    let free_x = L::and(c(pin.lim_x.0).le(tx), tx.le(c(pin.lim_x.1)));
    let free_y = L::and(c(pin.lim_y.0).le(ty), ty.le(c(pin.lim_y.1)));
    let inv_z = one.div(z);
    let (dsx_dx, dsx_dz) = (
        L::select(free_x, inv_z, zero),
        L::select(free_x, zero.sub(x).div(z2), zero),
    );
    let (dsy_dy, dsy_dz) = (
        L::select(free_y, inv_z, zero),
        L::select(free_y, zero.sub(y).div(z2), zero),
    );
    let (fx_z, fy_z) = (fx.div(z), fy.div(z));
    g_p[0] = g_p[0].sub(g_j0[1].mul(fx_z).mul(dsx_dx));
    g_p[1] = g_p[1].sub(g_j1[1].mul(fy_z).mul(dsy_dy));
    g_p[2] = g_p[2]
        .sub(g_j0[0].mul(fx).div(z2))
        .sub(g_j1[0].mul(fy).div(z2))
        .add(g_j0[1].mul(fx.mul(sx).div(z2).sub(fx_z.mul(dsx_dz))))
        .add(g_j1[1].mul(fy.mul(sy).div(z2).sub(fy_z.mul(dsy_dz))));

    // C = W C_world W^T: to the world covariance (W^T G_C W), and to the pose's rotation
    // (phi): C G_C - G_C C is antisymmetric, (C G_C)_ij - (C G_C)_ji.
    let w = splat33::<L>(&v.rotation);
    let g_cw = congruence(&w, &g_cc);
    let mut g_phi = [
        two.mul(sym_product(&sh.cov, &g_cc, 1, 2).sub(sym_product(&sh.cov, &g_cc, 2, 1))),
        two.mul(sym_product(&sh.cov, &g_cc, 2, 0).sub(sym_product(&sh.cov, &g_cc, 0, 2))),
        two.mul(sym_product(&sh.cov, &g_cc, 0, 1).sub(sym_product(&sh.cov, &g_cc, 1, 0))),
    ];

    // C_world = M M^T with M = R S (M's column j is R's column j times s_j): to the scales
    // (G_M's column j . R's column j, times s_j) and to R (G_M's column j times s_j), then to
    // the quaternion through its normalisation.
    let rc = &sh.rot_cols;
    let scale = sh.scale;
    let gm = twice_sym_times_m(&g_cw, rc, &scale);
    let g_log_scale = [
        dot3([gm[0][0], gm[1][0], gm[2][0]], rc[0]).mul(scale[0]),
        dot3([gm[0][1], gm[1][1], gm[2][1]], rc[1]).mul(scale[1]),
        dot3([gm[0][2], gm[1][2], gm[2][2]], rc[2]).mul(scale[2]),
    ];
    let gr = scale_columns(&gm, &scale);
    let [qw, qx, qy, qz] = sh.q;
    let g_qn = quat_vjp(sh.q, &gr);
    let along = g_qn[0]
        .mul(qw)
        .add(g_qn[1].mul(qx))
        .add(g_qn[2].mul(qy))
        .add(g_qn[3].mul(qz));
    let g_quat = [
        g_qn[0].sub(qw.mul(along)).div(sh.q_norm),
        g_qn[1].sub(qx.mul(along)).div(sh.q_norm),
        g_qn[2].sub(qy.mul(along)).div(sh.q_norm),
        g_qn[3].sub(qz.mul(along)).div(sh.q_norm),
    ];

    // Colour: the SH coefficients, and the view direction (to the mean and the camera
    // centre). A channel clamped at 0 passes no gradient.
    let nc = v.g.sh_coeffs * 3;
    let mut g_sh = [zero; WIDEST_ROW];
    let mut g_mean = [zero; 3];
    let mut g_rho = [zero; 3];
    if v.color {
        let col = colour(v, rows, &ce.mean);
        let gc = [
            L::select(zero.lt(col.raw(0)), load(s(|g| g.color.x)), zero),
            L::select(zero.lt(col.raw(1)), load(s(|g| g.color.y)), zero),
            L::select(zero.lt(col.raw(2)), load(s(|g| g.color.z)), zero),
        ];
        for k in 0..col.used {
            for ch in 0..3 {
                g_sh[3 * k + ch] = col.basis[k].mul(gc[ch]);
            }
        }
        if v.sh_degree > 0 {
            let mut db = [[zero; 3]; 16];
            sh::basis_grad_lanes(v.sh_degree, col.dir, &mut db);
            let mut g_dir = [zero; 3];
            for (k, dbk) in db.iter().enumerate().take(col.used) {
                let weight = dot3(
                    [
                        col.coeffs[3 * k],
                        col.coeffs[3 * k + 1],
                        col.coeffs[3 * k + 2],
                    ],
                    gc,
                );
                for (o, d) in g_dir.iter_mut().zip(dbk) {
                    *o = o.add(d.mul(weight));
                }
            }
            // Through the normalisation d = v / |v|; nothing where the direction has no length.
            let along = dot3(col.dir, g_dir);
            let g_v = [
                g_dir[0].sub(col.dir[0].mul(along)).mul(col.rcp),
                g_dir[1].sub(col.dir[1].mul(along)).mul(col.rcp),
                g_dir[2].sub(col.dir[2].mul(along)).mul(col.rcp),
            ];
            let g_v = [
                L::select(col.finite, g_v[0], zero),
                L::select(col.finite, g_v[1], zero),
                L::select(col.finite, g_v[2], zero),
            ];
            for i in 0..3 {
                g_mean[i] = g_mean[i].add(g_v[i]);
                g_rho[i] = dot3(w[i], g_v);
            }
        }
    }

    // p_cam = W mean + t: to the mean, and to the pose (rho, then phi by p_cam x g_p).
    for i in 0..3 {
        g_mean[i] = g_mean[i].add(dot3([w[0][i], w[1][i], w[2][i]], g_p));
        g_rho[i] = g_rho[i].add(g_p[i]);
    }
    g_phi[0] = g_phi[0].add(y.mul(g_p[2]).sub(z.mul(g_p[1])));
    g_phi[1] = g_phi[1].add(z.mul(g_p[0]).sub(x.mul(g_p[2])));
    g_phi[2] = g_phi[2].add(x.mul(g_p[1]).sub(y.mul(g_p[0])));

    let g_mean = [lanes(g_mean[0]), lanes(g_mean[1]), lanes(g_mean[2])];
    let g_log_scale = [
        lanes(g_log_scale[0]),
        lanes(g_log_scale[1]),
        lanes(g_log_scale[2]),
    ];
    let g_quat = [
        lanes(g_quat[0]),
        lanes(g_quat[1]),
        lanes(g_quat[2]),
        lanes(g_quat[3]),
    ];
    let g_logit = lanes(g_logit);
    let mut g_sh_lanes = [[0.0; LANES]; WIDEST_ROW];
    for (o, v) in g_sh_lanes.iter_mut().zip(&g_sh).take(nc) {
        *o = lanes(*v);
    }
    let parts = [
        lanes(g_rho[0]),
        lanes(g_rho[1]),
        lanes(g_rho[2]),
        lanes(g_phi[0]),
        lanes(g_phi[1]),
        lanes(g_phi[2]),
    ];
    for l in (0..count).filter(|l| on >> l & 1 != 0) {
        let rows = [
            (&mut out.mean[3 * l..3 * l + 3], &g_mean[..]),
            (&mut out.log_scale[3 * l..3 * l + 3], &g_log_scale[..]),
            (&mut out.quat[4 * l..4 * l + 4], &g_quat[..]),
            (&mut out.opacity_logit[l..l + 1], &[g_logit][..]),
            (&mut out.sh[nc * l..nc * (l + 1)], &g_sh_lanes[..nc]),
        ];
        for (row, values) in rows {
            for (o, v) in row.iter_mut().zip(values) {
                *o = v[l];
            }
        }
        for (p, part) in pose.iter_mut().zip(&parts) {
            *p += part[l];
        }
    }
}
