//! Pose-graph optimisation: keyframe chains of 100, 300 and 500 nodes circling a room (40
//! keyframes a lap, 5 cm higher each lap) with noisy, slightly biased odometry, and loop edges
//! (10% of the nodes) from a keyframe to one of an earlier lap near the same place; 2 of the loop
//! edges are false (0.5 m and 20 degrees off). Default options: the solve, the outlier rounds and
//! the checks, single-threaded (the solver uses no threads). Beside it, what a dense solve
//! would cost: one nalgebra Cholesky of the 6n x 6n normal equations (the solver needs one per
//! iteration, ~10 per optimisation).
//!
//! cargo bench -p legslam-core --bench graph

use legslam_core::camera::{se3, Pose};
use legslam_core::graph::{optimize, Edge, EdgeKind, PoseGraph, PoseGraphConfig};
use legslam_core::rng::Rng;
use nalgebra::{DMatrix, Matrix6, Vector6};

const LAP: usize = 40;

fn twist(v: [f64; 6]) -> Vector6<f64> {
    Vector6::from_column_slice(&v)
}

fn graph(n: usize) -> PoseGraph {
    let mut rng = Rng::new(n as u64);
    let truth: Vec<Pose> = (0..n)
        .map(|k| {
            let a = 2.0 * std::f64::consts::PI * (k % LAP) as f64 / LAP as f64;
            let mut t = se3::exp(&twist([0.0, 0.0, 0.0, 0.0, 0.0, a]))
                * se3::exp(&twist([
                    0.0,
                    0.0,
                    0.0,
                    -std::f64::consts::FRAC_PI_2,
                    0.0,
                    0.0,
                ]));
            t[(0, 3)] = 2.0 * a.cos();
            t[(1, 3)] = 2.0 * a.sin();
            t[(2, 3)] = 1.5 + 0.05 * (k / LAP) as f64;
            t
        })
        .collect();
    let (st, sr) = (0.01, 0.0087);
    let info = Matrix6::from_diagonal(&twist([
        1.0 / (st * st),
        1.0 / (st * st),
        1.0 / (st * st),
        1.0 / (sr * sr),
        1.0 / (sr * sr),
        1.0 / (sr * sr),
    ]));
    let noisy = |z: Pose, rng: &mut Rng| {
        let e = twist([0.0, 0.0, 0.0, 0.0, 0.0, 0.0].map(|_: f64| 0.5 * rng.normal()));
        let scaled = twist([
            st * e[0],
            st * e[1],
            st * e[2],
            sr * e[3],
            sr * e[4],
            sr * e[5],
        ]);
        z * se3::exp(&scaled)
    };
    let bias = se3::exp(&twist([0.001, 0.0, 0.0, 0.0, 0.002, 0.0]));
    let relative = |i: usize, j: usize| se3::inverse(&truth[i]) * truth[j];
    let mut edges: Vec<Edge> = (1..n)
        .map(|k| Edge {
            from: k - 1,
            to: k,
            measurement: noisy(relative(k - 1, k) * bias, &mut rng),
            information: info,
            kind: EdgeKind::Odometry,
        })
        .collect();
    let loops = n / 10;
    for l in 0..loops {
        let to = LAP + rng.below(n - LAP);
        let from = (to % LAP + LAP * rng.below(to / LAP) + rng.below(3)).min(to - 5);
        let mut measurement = noisy(relative(from, to), &mut rng);
        if l < 2 {
            measurement = se3::exp(&twist([0.5, 0.0, 0.0, 0.0, 0.35, 0.0])) * measurement;
        }
        edges.push(Edge {
            from,
            to,
            measurement,
            information: info,
            kind: EdgeKind::Loop,
        });
    }
    let mut poses = vec![truth[0]];
    for e in &edges[..n - 1] {
        poses.push(poses[poses.len() - 1] * e.measurement);
    }
    PoseGraph {
        poses,
        fixed: vec![0],
        edges,
    }
}

fn main() {
    for n in [100, 300, 500] {
        let r = optimize(&graph(n), &PoseGraphConfig::default()).unwrap();
        eprintln!(
            "{n} nodes: {} edges, {} iterations, rejected {:?}, cost {:.1} -> {:.1}",
            r.chi2.len(),
            r.iterations,
            r.rejected,
            r.initial_cost,
            r.final_cost
        );
    }
    divan::main();
}

#[divan::bench(args = [100, 300, 500], sample_count = 20, sample_size = 1)]
fn optimize_chain_with_loops(bencher: divan::Bencher, n: usize) {
    let g = graph(n);
    let config = PoseGraphConfig::default();
    bencher.bench(|| optimize(&g, &config).unwrap());
}

#[divan::bench(args = [100, 300, 500], sample_count = 3, sample_size = 1)]
fn dense_cholesky_6n(bencher: divan::Bencher, n: usize) {
    // Its cost does not depend on the values: a diagonally dominant symmetric matrix.
    let m = 6 * n;
    let a = DMatrix::from_fn(m, m, |i, j| {
        if i == j {
            m as f64
        } else {
            1.0 / (1 + i + j) as f64
        }
    });
    bencher.bench(|| a.clone().cholesky().unwrap());
}
