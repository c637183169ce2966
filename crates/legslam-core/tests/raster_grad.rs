//! Hand-written gradients against central finite differences, in f64 (run with
//! `cargo test -p legslam-core --features f64`), for every parameter group, every rendered
//! output and the camera pose, on random and on hard scenes.
#![cfg(feature = "f64")]

mod common;

use common::{hard_scene, random_scene, Rng, Scene};
use legslam_core::raster::{backward, render, Gradients, ImageGrads, RenderOptions};
use legslam_core::Real;
use nalgebra::{Matrix4, Rotation3, Vector3};

const H: f64 = 1e-6;

/// Random per-pixel weights of a linear loss on the requested outputs.
struct Weights {
    color: Option<Vec<f64>>,
    depth: Option<Vec<f64>>,
    alpha: Option<Vec<f64>>,
    features: Option<Vec<f64>>,
}

#[derive(Clone, Copy)]
struct Which {
    color: bool,
    depth: bool,
    alpha: bool,
    features: bool,
}

const ALL: Which = Which {
    color: true,
    depth: true,
    alpha: true,
    features: true,
};

/// Loss weights for each output; the features' image is laid out as `at` says.
fn weights(s: &Scene, which: Which, seed: u64, at: Sampling) -> Weights {
    let scale = at.scale;
    let mut rng = Rng::new(seed);
    let npix = s.intr.width * s.intr.height;
    let feature_pix = (s.intr.width / scale) * (s.intr.height / scale);
    let mut gen = |on: bool, n: usize| on.then(|| (0..n).map(|_| rng.normal()).collect());
    Weights {
        color: gen(which.color, npix * 3),
        depth: gen(which.depth, npix),
        alpha: gen(which.alpha, npix),
        features: gen(which.features && s.k > 0, feature_pix * s.k),
    }
}

fn loss(s: &Scene, deg: usize, at: Sampling, w: &Weights) -> f64 {
    let r = render(&s.gaussians(), &s.camera(), &opts(deg, at)).unwrap();
    let dot = |a: &[f64], b: &Option<Vec<f64>>| {
        b.as_ref()
            .map_or(0.0, |b| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>())
    };
    dot(&r.color, &w.color)
        + dot(&r.depth, &w.depth)
        + dot(&r.alpha, &w.alpha)
        + dot(&r.features, &w.features)
}

/// Where the features' pixels lie: `scale` times coarser, each the render of its block
/// (`origin` None) or the main layer's image at the point (s i + origin[0], s j + origin[1]).
#[derive(Clone, Copy)]
struct Sampling {
    scale: usize,
    origin: Option<[Real; 2]>,
}

/// Features at every pixel of the main layer.
const FULL: Sampling = Sampling {
    scale: 1,
    origin: None,
};

fn opts(deg: usize, at: Sampling) -> RenderOptions {
    // As a training loop renders (raster_kept.rs: the same gradients without).
    RenderOptions {
        sh_degree: deg,
        feature_scale: at.scale,
        feature_origin: at.origin,
        for_backward: true,
        ..Default::default()
    }
}

fn analytic(s: &Scene, deg: usize, at: Sampling, w: &Weights) -> Gradients {
    let r = render(&s.gaussians(), &s.camera(), &opts(deg, at)).unwrap();
    let grads = ImageGrads {
        color: w.color.as_deref(),
        depth: w.depth.as_deref(),
        alpha: w.alpha.as_deref(),
        features: w.features.as_deref(),
    };
    backward(&s.gaussians(), &s.camera(), &r, &grads).unwrap()
}

fn assert_close(what: &str, a: f64, fd: f64) {
    let err = (a - fd).abs();
    assert!(
        err <= 1e-6 + 1e-4 * fd.abs().max(a.abs()),
        "{what}: analytic {a} vs finite difference {fd}"
    );
}

/// Checks every entry of every parameter group and the pose; returns the largest gradient
/// magnitude seen per group, so that callers can assert that a group is reached at all.
fn check_all(s: &Scene, deg: usize, at: Sampling, w: &Weights) -> [f64; 7] {
    let g = analytic(s, deg, at, w);
    let mut largest = [0.0f64; 7];
    type Field = fn(&mut Scene) -> &mut Vec<f64>;
    let groups: [(&str, Field, &Vec<f64>); 6] = [
        ("means", |s| &mut s.means, &g.means),
        ("log_scales", |s| &mut s.log_scales, &g.log_scales),
        ("quats", |s| &mut s.quats, &g.quats),
        (
            "opacity_logits",
            |s| &mut s.opacity_logits,
            &g.opacity_logits,
        ),
        ("sh", |s| &mut s.sh, &g.sh),
        ("features", |s| &mut s.features, &g.features),
    ];
    for (gi, (name, field, grad)) in groups.iter().enumerate() {
        let mut p = s.clone();
        assert_eq!(field(&mut p).len(), grad.len(), "{name}: gradient size");
        for j in 0..grad.len() {
            let v = field(&mut p)[j];
            field(&mut p)[j] = v + H;
            let lp = loss(&p, deg, at, w);
            field(&mut p)[j] = v - H;
            let lm = loss(&p, deg, at, w);
            field(&mut p)[j] = v;
            assert_close(&format!("{name}[{j}]"), grad[j], (lp - lm) / (2.0 * H));
            largest[gi] = largest[gi].max(grad[j].abs());
        }
    }
    for a in 0..6 {
        let fd = (loss(&perturb_pose(s, a, H), deg, at, w)
            - loss(&perturb_pose(s, a, -H), deg, at, w))
            / (2.0 * H);
        assert_close(&format!("pose[{a}]"), g.pose[a], fd);
        largest[6] = largest[6].max(g.pose[a].abs());
    }
    largest
}

/// T_cw <- exp(xi^) T_cw with xi = h e_axis, (rho, phi) order.
fn perturb_pose(s: &Scene, axis: usize, h: f64) -> Scene {
    let mut xi = [0.0; 6];
    xi[axis] = h;
    let mut d = Matrix4::identity();
    let r = Rotation3::new(Vector3::new(xi[3], xi[4], xi[5]));
    d.fixed_view_mut::<3, 3>(0, 0).copy_from(r.matrix());
    d[(0, 3)] = xi[0];
    d[(1, 3)] = xi[1];
    d[(2, 3)] = xi[2];
    let mut out = s.clone();
    out.w2c = d * s.w2c;
    out
}

#[test]
fn gradients_on_random_scenes_all_outputs_all_sh_degrees() {
    for seed in 0..4u64 {
        let deg = seed as usize;
        let s = random_scene(100 + seed, 20, 36, 28, deg, 4);
        let largest = check_all(&s, deg, FULL, &weights(&s, ALL, seed, FULL));
        assert!(
            largest.iter().all(|v| *v > 0.0),
            "every group gets a gradient"
        );
    }
}

#[test]
fn gradients_on_hard_scenes() {
    for seed in 0..3u64 {
        let s = hard_scene(200 + seed, 40, 30, 2, 3);
        check_all(&s, 2, FULL, &weights(&s, ALL, seed, FULL));
    }
}

/// Each output on its own reaches geometry and opacity, not only its own values.
#[test]
fn each_output_alone_reaches_geometry_and_opacity() {
    let none = Which {
        color: false,
        depth: false,
        alpha: false,
        features: false,
    };
    let cases = [
        (
            "color",
            Which {
                color: true,
                ..none
            },
        ),
        (
            "depth",
            Which {
                depth: true,
                ..none
            },
        ),
        (
            "alpha",
            Which {
                alpha: true,
                ..none
            },
        ),
        (
            "features",
            Which {
                features: true,
                ..none
            },
        ),
    ];
    let s = random_scene(300, 12, 32, 24, 1, 3);
    for (name, which) in cases {
        let largest = check_all(&s, 1, FULL, &weights(&s, which, 7, FULL));
        for (gi, group) in ["means", "log_scales", "quats", "opacity_logits"]
            .iter()
            .enumerate()
        {
            assert!(largest[gi] > 1e-6, "{name} gradient does not reach {group}");
        }
        assert!(largest[6] > 1e-6, "{name} gradient does not reach the pose");
    }
}

/// Features rendered 2 and 3 times coarser (odd sizes, partial tiles) from the same projection,
/// as each block's render or point-sampled: their gradient reaches every group through the
/// coarse layer, alone and with the others.
#[test]
fn gradients_with_features_in_a_coarser_layer() {
    let features_only = Which {
        color: false,
        depth: false,
        alpha: false,
        features: true,
    };
    for (seed, scale, origin) in [
        (400u64, 2, None),
        (401, 3, None),
        (402, 2, Some([0.25, 1.0])),
        (403, 3, Some([1.6, -0.4])),
    ] {
        let at = Sampling { scale, origin };
        let s = random_scene(seed, 20, 37, 29, 1, 3);
        check_all(&s, 1, at, &weights(&s, ALL, seed, at));
        let largest = check_all(&s, 1, at, &weights(&s, features_only, seed, at));
        for (gi, group) in ["means", "log_scales", "quats", "opacity_logits"]
            .iter()
            .enumerate()
        {
            assert!(largest[gi] > 1e-6, "coarse features do not reach {group}");
        }
        assert!(largest[5] > 1e-6 && largest[6] > 1e-6);
    }
}
