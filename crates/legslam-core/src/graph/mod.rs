//! Pose-graph optimisation of keyframe poses, for loop closure.
//!
//! Nodes are camera-to-world poses [`Pose`] (`T_i`); some are fixed (at least one: the first
//! keyframe anchors the gauge). An [`Edge`] from `i` to `j` measures `Z = T_ij`, the pose of `j`
//! in `i`'s frame (`T_i^-1 T_j` when consistent), with a 6x6 information matrix `Omega`.
//!
//! **Conventions** (those of [`crate::camera::se3`]): the residual is the twist
//! `r = log(Z^-1 T_i^-1 T_j)`, *translation first* (`r = (v, w)`, metres then radians), and
//! `Omega` is in the same order; poses move by **left** perturbations `T <- exp(delta) T` (a
//! twist in world coordinates, as the tracker's). Jacobians are exact (the inverse right
//! Jacobian of SE(3), [`se3::right_jacobian_inverse`]); see [`edge_residual`].
//!
//! [`optimize`] minimises `1/2 sum chi2` over odometry edges plus the Cauchy-robustified
//! `1/2 sum rho(chi2)` over loop edges (`chi2 = r^T Omega r`) by Levenberg-Marquardt on the
//! block-sparse normal equations ([`solve`], [`cholesky`]), from the given poses (the odometry's,
//! against which a false loop stands out). Loop edges whose final `chi2` exceeds `outlier_chi2`
//! are then dropped and the graph solved again, until none is left; the result names them.
//!
//! The kernel judges loops against the odometry's information: a true loop whose misfit is far
//! beyond what that information allows (drift of many standard deviations: overconfident
//! odometry) looks like an outlier. Odometry information should describe its real error; a
//! larger `robust_scale` tolerates more drift at the price of weaker protection. (Graduated
//! non-convexity, annealing the scale down from least squares, was tried: on scenes with
//! strongly biased odometry it kept more true loops, but it let more false ones in and took
//! twice the iterations.)

mod cholesky;
mod residual;
mod solve;

use std::time::Instant;

use nalgebra::{Matrix3, Matrix6};

pub use residual::edge_residual;

use crate::camera::{se3, Pose};
use residual::cauchy;
use solve::{cost, edge_chi2, Problem};

/// What an edge comes from: loop edges get the robust kernel and may be rejected; odometry
/// edges (consecutive keyframes) are trusted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EdgeKind {
    Odometry,
    Loop,
}

/// Inverse covariance of an edge's residual twist (translation first): symmetric positive
/// definite.
pub type Information = Matrix6<f64>;

/// A relative-pose measurement between two nodes.
#[derive(Clone, Debug, PartialEq)]
pub struct Edge {
    pub from: usize,
    pub to: usize,
    /// `T_ij`: the pose of node `to` in the frame of node `from`.
    pub measurement: Pose,
    pub information: Information,
    pub kind: EdgeKind,
}

/// Keyframe poses (camera-to-world), which of them are fixed, and the edges between them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PoseGraph {
    pub poses: Vec<Pose>,
    pub fixed: Vec<usize>,
    pub edges: Vec<Edge>,
}

impl PoseGraph {
    /// Checks the graph can be optimised: rigid finite poses and measurements, edges between
    /// existing distinct nodes with symmetric positive definite information, and every node
    /// tied to a fixed one. The message names the node or edge.
    pub fn validate(&self) -> Result<(), String> {
        let n = self.poses.len();
        for (i, p) in self.poses.iter().enumerate() {
            se3::validate_pose(p, &format!("pose {i}"))?;
        }
        if self.fixed.is_empty() {
            return Err("at least one node must be fixed (the gauge: usually the first)".into());
        }
        if let Some(&f) = self.fixed.iter().find(|&&f| f >= n) {
            return Err(format!(
                "fixed node {f} does not exist: the graph has {n} nodes"
            ));
        }
        if self.edges.is_empty() {
            return Err("the pose graph has no edges: nothing to optimise".into());
        }
        for (k, e) in self.edges.iter().enumerate() {
            if e.from >= n || e.to >= n {
                return Err(format!(
                    "edge {k} joins nodes {} and {}, but the graph has {n} nodes",
                    e.from, e.to
                ));
            }
            if e.from == e.to {
                return Err(format!("edge {k} joins node {} to itself", e.from));
            }
            se3::validate_pose(&e.measurement, &format!("edge {k} measurement"))?;
            check_information(&e.information).map_err(|m| format!("edge {k} information {m}"))?;
        }
        let all: Vec<usize> = (0..self.edges.len()).collect();
        if let Some(v) = unanchored(self, &all) {
            return Err(format!(
                "node {v} is not connected to a fixed node by edges: its pose is undetermined"
            ));
        }
        Ok(())
    }
}

/// Why an information matrix is unusable, if it is.
fn check_information(m: &Information) -> Result<(), String> {
    if m.iter().any(|v| !v.is_finite()) {
        return Err("must be finite".into());
    }
    if (m - m.transpose()).amax() > 1e-9 * m.amax() {
        return Err("must be symmetric".into());
    }
    if m.cholesky().is_none() {
        return Err("must be positive definite".into());
    }
    Ok(())
}

/// The first node joined to no fixed node by the edges `active`, if any (union-find).
fn unanchored(graph: &PoseGraph, active: &[usize]) -> Option<usize> {
    let n = graph.poses.len();
    let mut parent: Vec<usize> = (0..n).collect();
    fn root(parent: &mut [usize], mut v: usize) -> usize {
        while parent[v] != v {
            parent[v] = parent[parent[v]];
            v = parent[v];
        }
        v
    }
    for &e in active {
        let (a, b) = (
            root(&mut parent, graph.edges[e].from),
            root(&mut parent, graph.edges[e].to),
        );
        parent[a] = b;
    }
    let mut anchored = vec![false; n];
    for &f in &graph.fixed {
        let r = root(&mut parent, f);
        anchored[r] = true;
    }
    (0..n).find(|&v| {
        let r = root(&mut parent, v);
        !anchored[r]
    })
}

/// Settings of [`optimize`].
#[derive(Clone, Debug, PartialEq)]
pub struct PoseGraphConfig {
    /// Levenberg-Marquardt steps per solve (one solve per kernel scale and per rejection round).
    pub max_iterations: usize,
    /// A solve stops when a step lowers the cost by less than this fraction of it.
    pub tolerance: f64,
    /// Scale of the Cauchy kernel on loop edges, in units of the Mahalanobis norm
    /// `sqrt(chi2)`; 0 turns the kernel off (plain least squares).
    pub robust_scale: f64,
    /// Drop loop edges whose final `chi2` exceeds `outlier_chi2` and solve again.
    pub reject_outliers: bool,
    pub outlier_chi2: f64,
}

impl Default for PoseGraphConfig {
    fn default() -> Self {
        PoseGraphConfig {
            max_iterations: 100,
            // Pose graphs converge fast near the optimum: the steps after this one move poses by
            // hundredths of a standard deviation.
            tolerance: 1e-6,
            // On 200 scenes like those of tests/graph.rs (two laps, odometry biased by up to 1
            // sigma a keyframe, 4 true and 3 false loops each), scale 2 / 3 / 4 rejected 598 /
            // 597 / 590 of the 600 false loops and kept 794 / 798 / 796 of the 800 true ones;
            // with a 2-sigma bias, 2 kept only 65% of the true loops and 3 kept 98%.
            robust_scale: 3.0,
            reject_outliers: true,
            // The 99% quantile of chi2 with 6 degrees of freedom.
            outlier_chi2: 16.81,
        }
    }
}

impl PoseGraphConfig {
    /// Checks the options' values; the message names the offending one.
    pub fn validate(&self) -> Result<(), String> {
        crate::options::check_finite("pose_graph", self)?;
        if self.max_iterations == 0 {
            return Err("pose_graph option max_iterations must be at least 1".into());
        }
        for (name, v) in [
            ("tolerance", self.tolerance),
            ("robust_scale", self.robust_scale),
        ] {
            if v < 0.0 {
                return Err(format!("pose_graph option {name} must be >= 0, got {v}"));
            }
        }
        if self.outlier_chi2 <= 0.0 {
            return Err(format!(
                "pose_graph option outlier_chi2 must be positive, got {}",
                self.outlier_chi2
            ));
        }
        Ok(())
    }
}

// Every option of [`PoseGraphConfig`] by name (see [`crate::options`]).
crate::options!(PoseGraphConfig, "pose_graph", {
    "max_iterations" => max_iterations,
    "tolerance" => tolerance,
    "robust_scale" => robust_scale,
    "reject_outliers" => reject_outliers,
    "outlier_chi2" => outlier_chi2,
});

/// The outcome of [`optimize`]. Per-edge values are indexed like the graph's edges.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseGraphResult {
    /// Optimised camera-to-world poses; fixed ones as given (bit for bit, unless their
    /// rotation had to be projected onto SO(3)).
    pub poses: Vec<Pose>,
    /// Each edge's `chi2 = r^T Omega r` at the optimised poses (rejected edges included).
    pub chi2: Vec<f64>,
    /// Each edge's final weight on its information: 1 for odometry, the kernel's for loop
    /// edges, 0 for rejected ones.
    pub weights: Vec<f64>,
    /// Loop edges dropped as outliers, in the order they were found.
    pub rejected: Vec<usize>,
    /// Levenberg-Marquardt steps over all solves.
    pub iterations: usize,
    /// The cost `F` at the given poses over every edge, and at the optimised poses over the
    /// edges kept (kernel at `robust_scale`).
    pub initial_cost: f64,
    pub final_cost: f64,
    /// Whether the last solve met the tolerance within `max_iterations`.
    pub converged: bool,
    /// Wall time of [`optimize`] (s).
    pub seconds: f64,
}

/// `p` with its rotation projected onto SO(3) when it is off by more than rounding (poses read
/// at text precision), else `p` itself, bit for bit.
fn rigid(p: &Pose) -> Pose {
    let r: Matrix3<f64> = se3::rotation(p);
    if (r.transpose() * r - Matrix3::identity()).amax() > 1e-12 {
        se3::orthonormalize(p)
    } else {
        *p
    }
}

/// Optimises the free poses of `graph`; see the module docs for the cost and the steps.
pub fn optimize(graph: &PoseGraph, config: &PoseGraphConfig) -> Result<PoseGraphResult, String> {
    let clock = Instant::now();
    config.validate()?;
    graph.validate()?;
    let mut fixed = vec![false; graph.poses.len()];
    for &f in &graph.fixed {
        fixed[f] = true;
    }
    let z_inv: Vec<Pose> = graph
        .edges
        .iter()
        .map(|e| se3::inverse(&rigid(&e.measurement)))
        .collect();
    let mut poses: Vec<Pose> = graph.poses.iter().map(rigid).collect();
    let c = config.robust_scale;
    let mut active: Vec<usize> = (0..graph.edges.len()).collect();
    let initial_cost = cost(graph, &z_inv, &active, &poses, c);
    let is_loop = |e: usize| graph.edges[e].kind == EdgeKind::Loop;
    let (mut rejected, mut iterations) = (Vec::new(), 0);
    let converged = loop {
        let m = Problem::new(graph, &z_inv, &active, &fixed).minimize(&mut poses, c, config);
        iterations += m.iterations;
        if !config.reject_outliers {
            break m.converged;
        }
        let mut outliers: Vec<(f64, usize)> = active
            .iter()
            .filter(|&&e| is_loop(e))
            .map(|&e| (edge_chi2(graph, &z_inv, e, &poses), e))
            .filter(|&(chi2, _)| chi2 > config.outlier_chi2)
            .collect();
        outliers.sort_by(|a, b| b.0.total_cmp(&a.0));
        let before = rejected.len();
        for (_, e) in outliers {
            // An edge whose loss would cut nodes off from every fixed one stays: nothing else
            // could place them.
            let kept: Vec<usize> = active.iter().copied().filter(|&a| a != e).collect();
            if unanchored(graph, &kept).is_none() {
                active = kept;
                rejected.push(e);
            }
        }
        if rejected.len() == before {
            break m.converged;
        }
    };
    let chi2: Vec<f64> = (0..graph.edges.len())
        .map(|e| edge_chi2(graph, &z_inv, e, &poses))
        .collect();
    let weights = chi2
        .iter()
        .enumerate()
        .map(|(e, &x)| match graph.edges[e].kind {
            _ if rejected.contains(&e) => 0.0,
            EdgeKind::Odometry => 1.0,
            EdgeKind::Loop => cauchy(x, c).1,
        })
        .collect();
    let final_cost = cost(graph, &z_inv, &active, &poses, c);
    Ok(PoseGraphResult {
        poses,
        chi2,
        weights,
        rejected,
        iterations,
        initial_cost,
        final_cost,
        converged,
        seconds: clock.elapsed().as_secs_f64(),
    })
}
