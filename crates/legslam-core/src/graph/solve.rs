//! Levenberg-Marquardt over the free poses of a graph, for a fixed set of edges: the normal
//! equations assembled in 6x6 blocks and solved by the block-sparse Cholesky of [`super::cholesky`].
//!
//! Cost `F = 1/2 sum_e rho_e(chi2_e)` with `chi2_e = r_e^T Omega_e r_e`, `rho = chi2` for odometry
//! edges and the Cauchy kernel for loop edges (iteratively reweighted: each iteration weighs a
//! loop edge's information by the kernel's `w` at the current poses). Steps are left twists,
//! `T <- exp(delta) T`; the damping is Marquardt's, `H + lambda diag(H)`, which is blind to the
//! units (metres, radians) of the twist; `lambda` follows Nielsen's gain-ratio rule.

use nalgebra::{Matrix6, Vector6};

use super::cholesky::Pattern;
use super::residual::{cauchy, jacobian_to, residual};
use super::{EdgeKind, PoseGraph, PoseGraphConfig};
use crate::camera::{se3, Pose};

/// Starting damping (relative to the diagonal of `H`): close to Gauss-Newton, which converges in
/// a few steps on pose graphs; failed steps raise it.
const LAMBDA0: f64 = 1e-4;
/// Past this damping a step is too small to change the cost in f64: a minimum.
const LAMBDA_MAX: f64 = 1e20;

/// Edge `e`'s residual at `poses`.
fn edge_r(graph: &PoseGraph, z_inv: &[Pose], e: usize, poses: &[Pose]) -> Vector6<f64> {
    let edge = &graph.edges[e];
    residual(&poses[edge.from], &poses[edge.to], &z_inv[e])
}

/// Edge `e`'s squared Mahalanobis norm at `poses`.
pub(crate) fn edge_chi2(graph: &PoseGraph, z_inv: &[Pose], e: usize, poses: &[Pose]) -> f64 {
    let r = edge_r(graph, z_inv, e, poses);
    r.dot(&(graph.edges[e].information * r))
}

/// Edge `e`'s cost term `rho(chi2)` and information weight `w` for residual `r`, kernel scale `c`.
fn edge_cost(graph: &PoseGraph, e: usize, r: &Vector6<f64>, c: f64) -> (f64, f64) {
    let edge = &graph.edges[e];
    let chi2 = r.dot(&(edge.information * r));
    match edge.kind {
        EdgeKind::Odometry => (chi2, 1.0),
        EdgeKind::Loop => cauchy(chi2, c),
    }
}

/// `F` over the edges `active` at `poses` with kernel scale `c`.
pub(crate) fn cost(
    graph: &PoseGraph,
    z_inv: &[Pose],
    active: &[usize],
    poses: &[Pose],
    c: f64,
) -> f64 {
    0.5 * active
        .iter()
        .map(|&e| edge_cost(graph, e, &edge_r(graph, z_inv, e, poses), c).0)
        .sum::<f64>()
}

/// The least-squares problem over a set of edges: which poses are variables, and the symbolic
/// factorisation of its normal equations.
pub(crate) struct Problem<'a> {
    graph: &'a PoseGraph,
    /// Inverse measurements `Z^-1` of every edge.
    z_inv: &'a [Pose],
    /// The edges in the cost.
    active: &'a [usize],
    /// Variable index of each node (`None`: fixed), and node of each variable.
    var: Vec<Option<usize>>,
    nodes: Vec<usize>,
    pattern: Pattern,
}

/// What [`Problem::minimize`] did.
pub(crate) struct Minimized {
    /// Steps tried (each one linear solve).
    pub iterations: usize,
    pub converged: bool,
}

impl<'a> Problem<'a> {
    pub fn new(
        graph: &'a PoseGraph,
        z_inv: &'a [Pose],
        active: &'a [usize],
        fixed: &[bool],
    ) -> Self {
        let nodes: Vec<usize> = (0..fixed.len()).filter(|&v| !fixed[v]).collect();
        let mut var = vec![None; fixed.len()];
        for (k, &v) in nodes.iter().enumerate() {
            var[v] = Some(k);
        }
        let pairs = active.iter().filter_map(|&e| {
            let edge = &graph.edges[e];
            Some((var[edge.from]?, var[edge.to]?))
        });
        let pattern = Pattern::new(nodes.len(), pairs);
        Problem {
            graph,
            z_inv,
            active,
            var,
            nodes,
            pattern,
        }
    }

    /// The residuals of the active edges at `poses`, and the cost they give.
    fn residuals(&self, poses: &[Pose], c: f64) -> (Vec<Vector6<f64>>, f64) {
        let r: Vec<Vector6<f64>> = self
            .active
            .iter()
            .map(|&e| edge_r(self.graph, self.z_inv, e, poses))
            .collect();
        let f = self
            .active
            .iter()
            .zip(&r)
            .map(|(&e, r)| 0.5 * edge_cost(self.graph, e, r, c).0)
            .sum();
        (r, f)
    }

    /// The normal equations at `poses` with residuals `r` (from [`Problem::residuals`]) into `h`
    /// (the blocks of `H` as the pattern lays them out) and `g` (`J^T W r` by variable).
    fn normal_equations(
        &self,
        poses: &[Pose],
        r: &[Vector6<f64>],
        c: f64,
        h: &mut [Matrix6<f64>],
        g: &mut [Vector6<f64>],
    ) {
        let p = &self.pattern;
        h.fill(Matrix6::zeros());
        g.fill(Vector6::zeros());
        for (&e, r) in self.active.iter().zip(r) {
            let edge = &self.graph.edges[e];
            let w = edge_cost(self.graph, e, r, c).1;
            let jj = jacobian_to(r, &poses[edge.to]);
            // J_i = -J_j, so the edge adds A = J_j^T W J_j to both diagonal blocks, -A between
            // them, and -+J_j^T W r to the gradients.
            let jtw = jj.transpose() * (edge.information * w);
            let a = jtw * jj;
            let jtwr = jtw * r;
            let (vi, vj) = (self.var[edge.from], self.var[edge.to]);
            if let Some(i) = vi {
                h[p.block(i, i)] += a;
                g[i] -= jtwr;
            }
            if let Some(j) = vj {
                h[p.block(j, j)] += a;
                g[j] += jtwr;
            }
            if let (Some(i), Some(j)) = (vi, vj) {
                h[p.block(i, j)] -= a;
            }
        }
    }

    /// Minimises the cost with loop kernel scale `c` from `poses` (updated in place).
    pub fn minimize(&self, poses: &mut [Pose], c: f64, config: &PoseGraphConfig) -> Minimized {
        let n = self.nodes.len();
        let (mut lambda, mut nu) = (LAMBDA0, 2.0);
        let mut iterations = 0;
        let (mut h, mut damped) = (vec![Matrix6::zeros(); self.pattern.len()], Vec::new());
        let mut g = vec![Vector6::zeros(); n];
        let (mut r, mut f) = self.residuals(poses, c);
        self.normal_equations(poses, &r, c, &mut h, &mut g);
        let mut moved = poses.to_vec();
        while iterations < config.max_iterations {
            if f == 0.0 {
                return Minimized {
                    iterations,
                    converged: true,
                };
            }
            damped.clone_from(&h);
            for k in 0..n {
                let d = &mut damped[self.pattern.block(k, k)];
                for i in 0..6 {
                    d[(i, i)] *= 1.0 + lambda;
                }
            }
            iterations += 1;
            if !self.pattern.factor(&mut damped) {
                (lambda, nu) = (lambda * nu, nu * 2.0);
                continue;
            }
            let neg_g: Vec<Vector6<f64>> = g.iter().map(|v| -v).collect();
            let delta = self.pattern.solve(&damped, &neg_g);
            // Predicted decrease of the quadratic model: delta^T (lambda D delta - g) / 2.
            let predicted: f64 = (0..n)
                .map(|k| {
                    let d = h[self.pattern.block(k, k)].diagonal();
                    let dk = &delta[k];
                    0.5 * (lambda * dk.dot(&d.component_mul(dk)) - dk.dot(&g[k]))
                })
                .sum();
            for (k, &v) in self.nodes.iter().enumerate() {
                moved[v] = se3::exp(&delta[k]) * poses[v];
            }
            if predicted <= config.tolerance * f {
                // The model expects less than the tolerance: the last step. Taken unchecked, as
                // so small a decrease is lost in the rounding of the cost it would be checked by.
                if predicted > 0.0 {
                    poses.copy_from_slice(&moved);
                }
                return Minimized {
                    iterations,
                    converged: true,
                };
            }
            let (r_new, f_new) = self.residuals(&moved, c);
            let gain = (f - f_new) / predicted;
            if gain > 0.0 {
                let done = f - f_new <= config.tolerance * f;
                poses.copy_from_slice(&moved);
                (r, f) = (r_new, f_new);
                lambda *= (1.0 - (2.0 * gain - 1.0).powi(3)).max(1.0 / 3.0);
                nu = 2.0;
                if done {
                    return Minimized {
                        iterations,
                        converged: true,
                    };
                }
                self.normal_equations(poses, &r, c, &mut h, &mut g);
            } else {
                (lambda, nu) = (lambda * nu, nu * 2.0);
                if lambda > LAMBDA_MAX {
                    return Minimized {
                        iterations,
                        converged: true,
                    };
                }
            }
        }
        Minimized {
            iterations,
            converged: false,
        }
    }
}
