//! Tests of the tracker on ray-cast synthetic RGB-D views.

use nalgebra::{Matrix4, Vector3, Vector6};

use super::solve::{eval_point, Params, RefLevel};
use super::*;
use crate::camera::Intrinsics;

const W: usize = 320;
const H: usize = 240;

fn intrinsics() -> Intrinsics {
    Intrinsics {
        fx: 290.0,
        fy: 290.0,
        cx: 159.5,
        cy: 119.5,
        width: W,
        height: H,
    }
}

/// A room (inside of a box) with two spheres, textured by smooth functions of position.
fn texture(p: &Vector3<f64>) -> [f64; 3] {
    let a = 0.5 + 0.2 * (5.0 * p.x + 1.0).sin() * (4.0 * p.y).cos() + 0.15 * (7.0 * p.z).sin();
    let b = 0.5 + 0.25 * (3.0 * p.y + 2.0 * p.z).sin();
    let c = 0.5 + 0.2 * (6.0 * p.x - 3.0 * p.z).cos();
    [a.clamp(0.0, 1.0), b.clamp(0.0, 1.0), c.clamp(0.0, 1.0)]
}

/// Ray-casts colour (f32 RGB) and z-depth of the scene from camera-to-world `pose`.
fn render(pose: &Matrix4<f64>, k: &Intrinsics) -> (Vec<f32>, Vec<f32>) {
    let lo = Vector3::new(-2.0, -1.5, -1.0);
    let hi = Vector3::new(2.0, 1.2, 3.0);
    let spheres = [
        (Vector3::new(-0.6, 0.3, 2.0), 0.45),
        (Vector3::new(0.7, -0.2, 1.6), 0.3),
    ];
    let r = se3::rotation(pose);
    let o = se3::translation(pose);
    let mut rgb = vec![0.0f32; 3 * k.width * k.height];
    let mut depth = vec![0.0f32; k.width * k.height];
    for y in 0..k.height {
        for x in 0..k.width {
            let dc = Vector3::new((x as f64 - k.cx) / k.fx, (y as f64 - k.cy) / k.fy, 1.0);
            let d = r * dc;
            // Exit distance from the inside of the box.
            let mut t = f64::INFINITY;
            for a in 0..3 {
                if d[a] > 1e-12 {
                    t = t.min((hi[a] - o[a]) / d[a]);
                } else if d[a] < -1e-12 {
                    t = t.min((lo[a] - o[a]) / d[a]);
                }
            }
            for (c, rad) in &spheres {
                let oc = o - c;
                let bq = oc.dot(&d);
                let cq = oc.norm_squared() - rad * rad;
                let a2 = d.norm_squared();
                let disc = bq * bq - a2 * cq;
                if disc > 0.0 {
                    let ts = (-bq - disc.sqrt()) / a2;
                    if ts > 0.0 && ts < t {
                        t = ts;
                    }
                }
            }
            let p = o + d * t;
            let i = y * k.width + x;
            depth[i] = t as f32; // dc.z == 1, so t is the z-depth
            let c = texture(&p);
            for ch in 0..3 {
                rgb[3 * i + ch] = c[ch] as f32;
            }
        }
    }
    (rgb, depth)
}

fn pose_of(xi: [f64; 6]) -> Matrix4<f64> {
    se3::exp(&Vector6::from_row_slice(&xi))
}

fn errors(a: &Matrix4<f64>, b: &Matrix4<f64>) -> (f64, f64) {
    let rel = se3::inverse(a) * b;
    (
        se3::translation(&rel).norm(),
        se3::rotation_angle(&rel).to_degrees(),
    )
}

fn setup(t_wr: &Matrix4<f64>, t_wf: &Matrix4<f64>, cfg: &TrackerConfig) -> (Reference, Frame) {
    let k = intrinsics();
    let (rgb_r, d_r) = render(t_wr, &k);
    let (rgb_f, d_f) = render(t_wf, &k);
    let r = Reference::new(Color::RgbF32(&rgb_r), &d_r, &k, t_wr, cfg).unwrap();
    let f = Frame::new(Color::RgbF32(&rgb_f), &d_f, &k, cfg).unwrap();
    (r, f)
}

fn test_config() -> TrackerConfig {
    TrackerConfig {
        finest_level: 0,
        levels: 3,
        iterations: vec![20, 20, 20],
        convergence_eps: 1e-8,
        ..TrackerConfig::default()
    }
}

#[test]
fn track_recovers_known_motion_synthetic() {
    let t_wr = pose_of([0.1, 0.05, 0.2, 0.05, -0.1, 0.02]);
    // 4 cm and about 2.5 degrees between the views.
    let t_wf = t_wr * pose_of([0.03, -0.02, 0.02, 0.02, 0.035, -0.015]);
    for cfg in [test_config(), TrackerConfig::default()] {
        let (r, f) = setup(&t_wr, &t_wf, &cfg);
        let res = track(&r, &f, &t_wr, &cfg).unwrap();
        let (et, er) = errors(&res.pose, &t_wf);
        assert!(!res.lost, "{res:?}");
        assert!(et < 1e-3 && er < 0.1, "error {et} m {er} deg, {res:?}");
        assert!(res.inlier_ratio > 0.8, "{res:?}");
        assert!(res.condition.is_finite() && res.condition > 1.0);
    }
}

#[test]
fn track_converges_from_perturbations() {
    let t_wr = pose_of([0.0, 0.0, 0.1, 0.0, 0.0, 0.0]);
    let t_wf = t_wr * pose_of([0.02, 0.01, -0.03, -0.01, 0.02, 0.01]);
    let cfg = test_config();
    let (r, f) = setup(&t_wr, &t_wf, &cfg);
    let perturbations = [
        [0.05, 0.0, 0.0, 0.0, 0.05, 0.0],
        [-0.04, 0.03, 0.05, 0.04, 0.0, -0.03],
        [0.0, -0.06, 0.0, -0.05, 0.0, 0.05],
    ];
    for p in perturbations {
        let init = t_wf * pose_of(p);
        let res = track(&r, &f, &init, &cfg).unwrap();
        let (et, er) = errors(&res.pose, &t_wf);
        assert!(!res.lost, "{p:?}: {res:?}");
        assert!(et < 1e-3 && er < 0.1, "{p:?}: error {et} m {er} deg");
    }
}

#[test]
fn track_geometry_only_and_photometry_heavy_both_converge() {
    let t_wr = pose_of([0.0, 0.1, 0.0, 0.0, 0.1, 0.0]);
    let t_wf = t_wr * pose_of([0.02, 0.0, 0.03, 0.0, -0.03, 0.01]);
    for w in [0.0, 1.0] {
        let cfg = TrackerConfig {
            photometric_weight: w,
            ..test_config()
        };
        let (r, f) = setup(&t_wr, &t_wf, &cfg);
        let res = track(&r, &f, &t_wr, &cfg).unwrap();
        let (et, er) = errors(&res.pose, &t_wf);
        assert!(et < 1e-3 && er < 0.1, "w={w}: {et} m {er} deg {res:?}");
    }
}

#[test]
fn track_all_invalid_depth_is_lost_without_nan() {
    let cfg = TrackerConfig::default();
    let t = pose_of([0.0; 6]);
    let k = intrinsics();
    let (rgb, d) = render(&t, &k);
    let r = Reference::new(Color::RgbF32(&rgb), &d, &k, &t, &cfg).unwrap();
    let zeros = vec![0.0f32; W * H];
    let mut nan = vec![f32::NAN; W * H];
    nan[5] = f32::INFINITY;
    for depth in [&zeros, &nan] {
        let f = Frame::new(Color::RgbF32(&rgb), depth, &k, &cfg).unwrap();
        let res = track(&r, &f, &t, &cfg).unwrap();
        assert!(res.lost);
        assert!(res.pose.iter().all(|v| v.is_finite()));
        assert!(res.residual_rms.is_finite() && res.inlier_ratio == 0.0);
        // And the other way round: an empty reference.
        let r0 = Reference::new(Color::RgbF32(&rgb), depth, &k, &t, &cfg).unwrap();
        let f1 = Frame::new(Color::RgbF32(&rgb), &d, &k, &cfg).unwrap();
        let res = track(&r0, &f1, &t, &cfg).unwrap();
        assert!(res.lost && res.pose.iter().all(|v| v.is_finite()));
    }
}

#[test]
fn track_unrelated_frame_is_lost() {
    // The frame is random depth and colour: no consistent alignment exists.
    let cfg = TrackerConfig::default();
    let t = pose_of([0.0; 6]);
    let k = intrinsics();
    let (rgb, d) = render(&t, &k);
    let r = Reference::new(Color::RgbF32(&rgb), &d, &k, &t, &cfg).unwrap();
    let mut s = 12345u64;
    let mut rnd = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 33) as f64 / (1u64 << 31) as f64) as f32
    };
    let rgb_f: Vec<f32> = (0..3 * W * H).map(|_| rnd()).collect();
    let d_f: Vec<f32> = (0..W * H).map(|_| 0.5 + 3.0 * rnd()).collect();
    let f = Frame::new(Color::RgbF32(&rgb_f), &d_f, &k, &cfg).unwrap();
    let res = track(&r, &f, &t, &cfg).unwrap();
    assert!(res.lost, "{res:?}");
    assert!(res.pose.iter().all(|v| v.is_finite()));
}

#[test]
fn track_textureless_plane_is_lost_as_degenerate() {
    // A uniformly coloured flat wall: sliding along it changes no residual, so the normal
    // equations are singular in those directions and the pose cannot be trusted.
    let cfg = TrackerConfig::default();
    let k = intrinsics();
    let t = pose_of([0.0; 6]);
    let rgb = vec![0.5f32; 3 * W * H];
    let d = vec![2.0f32; W * H];
    let r = Reference::new(Color::RgbF32(&rgb), &d, &k, &t, &cfg).unwrap();
    let f = Frame::new(Color::RgbF32(&rgb), &d, &k, &cfg).unwrap();
    let res = track(&r, &f, &t, &cfg).unwrap();
    assert!(res.lost, "{res:?}");
    assert!(res.condition > cfg.max_condition, "{res:?}");
    assert!(res.pose.iter().all(|v| v.is_finite()));
    // The textured synthetic room is well conditioned.
    let (rgb2, d2) = render(&t, &k);
    let r2 = Reference::new(Color::RgbF32(&rgb2), &d2, &k, &t, &cfg).unwrap();
    let f2 = Frame::new(Color::RgbF32(&rgb2), &d2, &k, &cfg).unwrap();
    let res2 = track(&r2, &f2, &t, &cfg).unwrap();
    assert!(!res2.lost && res2.condition < cfg.max_condition, "{res2:?}");
}

#[test]
fn track_rejects_bad_inputs() {
    let cfg = TrackerConfig::default();
    let k = intrinsics();
    let rgb = vec![0u8; 3 * W * H];
    let d = vec![1.0f32; W * H];
    assert!(Frame::new(Color::Rgb8(&rgb), &d[1..], &k, &cfg)
        .unwrap_err()
        .contains("depth"));
    assert!(Frame::new(Color::Rgb8(&rgb[3..]), &d, &k, &cfg)
        .unwrap_err()
        .contains("colour"));
    let bad_k = Intrinsics { fx: f64::NAN, ..k };
    assert!(Frame::new(Color::Rgb8(&rgb), &d, &bad_k, &cfg).is_err());
    let bad_cfg = TrackerConfig {
        geometric_huber: -1.0,
        ..cfg.clone()
    };
    assert!(Frame::new(Color::Rgb8(&rgb), &d, &k, &bad_cfg)
        .unwrap_err()
        .contains("geometric_huber"));
    let tiny = TrackerConfig {
        levels: 7,
        ..cfg.clone()
    };
    assert!(Frame::new(Color::Rgb8(&rgb), &d, &k, &tiny)
        .unwrap_err()
        .contains("too small"));
    let mut bad_pose = Matrix4::identity();
    bad_pose[(0, 0)] = 2.0;
    assert!(Reference::new(Color::Rgb8(&rgb), &d, &k, &bad_pose, &cfg).is_err());
    let f = Frame::new(Color::Rgb8(&rgb), &d, &k, &cfg).unwrap();
    let r = Reference::new(Color::Rgb8(&rgb), &d, &k, &Matrix4::identity(), &cfg).unwrap();
    assert!(track(&r, &f, &bad_pose, &cfg).is_err());
    let other = TrackerConfig {
        levels: 2,
        ..cfg.clone()
    };
    assert!(track(&r, &f, &Matrix4::identity(), &other).is_err());
}

#[test]
fn track_jacobians_match_finite_differences() {
    let cfg = TrackerConfig {
        photometric_weight: 1.0,
        ..test_config()
    };
    let t_wr = pose_of([0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    let t_wf = pose_of([0.005, 0.0, 0.0, 0.0, 0.002, 0.0]);
    let (r, f) = setup(&t_wr, &t_wf, &cfg);
    let rl = RefLevel {
        lev: &r.frame.levels[0],
        igd: &r.igd[0],
        normals: &r.normals[0],
    };
    let p = Params::new(&cfg);
    let fl = &f.levels[0];
    let t_rf = se3::inverse(&t_wr) * t_wf;
    let mut checked_geo = 0;
    let mut checked_photo = 0;
    // Pixels on smooth surfaces (not on a wall corner or a sphere's silhouette, where the
    // intensity is not differentiable).
    let smooth = |x: usize, y: usize| {
        (y - 3..=y + 3).all(|yy| {
            (x - 3..=x + 3).all(|xx| {
                let c = fl.depth[yy * fl.w + xx];
                let dx = fl.depth[yy * fl.w + xx + 1] + fl.depth[yy * fl.w + xx - 1] - 2.0 * c;
                let dy = fl.depth[(yy + 1) * fl.w + xx] + fl.depth[(yy - 1) * fl.w + xx] - 2.0 * c;
                dx.abs() < 2e-3 && dy.abs() < 2e-3
            })
        })
    };
    let pixels: Vec<(usize, usize)> = (0..40)
        .flat_map(|j| [(10 + 7 * j, 12 + 5 * j), (300 - 7 * j, 20 + 5 * j)])
        .filter(|&(x, y)| smooth(x, y))
        .collect();
    assert!(pixels.len() >= 10, "{} smooth test pixels", pixels.len());
    for (x, y) in pixels {
        let i = y * fl.w + x;
        let xf = fl.point(x, y, fl.depth[i]);
        let (rot, t) = to_f32(&t_rf);
        let base = eval_point(&rl, &xf, fl.intensity[i], &rot, &t, &p);
        for k in 0..6 {
            // Larger step for the geometric residual (linear in the pose but computed in
            // f32); association must stay the same pixel.
            let h = 1e-3;
            let mut d = Vector6::zeros();
            d[k] = h;
            let (rp, tp) = to_f32(&(se3::exp(&d) * t_rf));
            d[k] = -h;
            let (rm, tm) = to_f32(&(se3::exp(&d) * t_rf));
            let plus = eval_point(&rl, &xf, fl.intensity[i], &rp, &tp, &p);
            let minus = eval_point(&rl, &xf, fl.intensity[i], &rm, &tm, &p);
            let same = plus.pixel == base.pixel && minus.pixel == base.pixel;
            if let (true, Some(g0), Some(gp), Some(gm)) = (same, base.geo, plus.geo, minus.geo) {
                let num = (gp.0 - gm.0) as f64 / (2.0 * h);
                let ana = g0.1[k] as f64;
                assert!(
                    (num - ana).abs() < 2e-3 * (1.0 + ana.abs()),
                    "geometric d/dxi_{k} at ({x},{y}): {num} vs {ana}"
                );
                checked_geo += 1;
            }
            let hp = 1e-4;
            d = Vector6::zeros();
            d[k] = hp;
            let (rp, tp) = to_f32(&(se3::exp(&d) * t_rf));
            d[k] = -hp;
            let (rm, tm) = to_f32(&(se3::exp(&d) * t_rf));
            let plus = eval_point(&rl, &xf, fl.intensity[i], &rp, &tp, &p);
            let minus = eval_point(&rl, &xf, fl.intensity[i], &rm, &tm, &p);
            if let (Some(q0), Some(qp), Some(qm)) = (base.photo, plus.photo, minus.photo) {
                // The analytic Jacobian uses the central-difference image gradient, the
                // numeric one the bilinear interpolant: equal up to the smooth texture's
                // second-order terms.
                let num = (qp.0 - qm.0) as f64 / (2.0 * hp);
                let ana = q0.1[k] as f64;
                let scale = q0.1.iter().map(|v| v.abs()).fold(0.0f32, f32::max) as f64;
                assert!(
                    (num - ana).abs() < 0.1 * scale + 1e-3,
                    "photometric d/dxi_{k} at ({x},{y}): {num} vs {ana}"
                );
                checked_photo += 1;
            }
        }
    }
    assert!(
        checked_geo >= 40 && checked_photo >= 40,
        "{checked_geo} {checked_photo}"
    );
}

#[test]
fn track_reduction_is_deterministic_across_thread_counts() {
    let cfg = TrackerConfig::default();
    let t_wr = pose_of([0.0; 6]);
    let t_wf = pose_of([0.02, 0.01, 0.0, 0.0, 0.02, 0.0]);
    let (r, f) = setup(&t_wr, &t_wf, &cfg);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| track(&r, &f, &t_wr, &cfg).unwrap())
    };
    let a = run(1);
    let b = run(2);
    let c = run(3);
    assert_eq!(a, b);
    assert_eq!(a, c);
}

#[test]
fn track_odometry_follows_a_synthetic_path() {
    let k = intrinsics();
    let cfg = TrackerConfig::default();
    let start = pose_of([0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    let mut odo = Odometry::new(cfg.clone(), &start, true).unwrap();
    let step = pose_of([0.02, 0.0, 0.01, 0.0, 0.015, 0.005]);
    let mut gt = start;
    for i in 0..6 {
        let (rgb, d) = render(&gt, &k);
        let f = Frame::new(Color::RgbF32(&rgb), &d, &k, &cfg).unwrap();
        let out = odo.step(f).unwrap();
        assert_eq!(out.result.is_none(), i == 0);
        let (et, er) = errors(&out.pose, &gt);
        assert!(et < 2e-3 && er < 0.1, "frame {i}: {et} m {er} deg");
        gt *= step;
    }
    assert_eq!(odo.lost_frames(), 0);
    assert_eq!(odo.frames(), 6);
}

/// Process CPU time (user + system, all threads) in ms, from /proc (Linux; 0 elsewhere).
fn cpu_ms() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    // Fields 14 and 15 (utime, stime) are at 11 and 12 after the command name; 100 Hz.
    (ticks(11) + ticks(12)) * 10.0
}

/// Timing of the stages on a 640x480 synthetic view (run with `--ignored --nocapture`);
/// wall and CPU time per call, since the machine may be shared. Speed is measured here and
/// in benches/bench_tracking.py, never asserted.
/// The eight-pixel AVX2 pass against the scalar one: the same correspondences (counts), the
/// same normal equations to rounding, at every level of frames with holes in their depth, on a
/// width that leaves a tail after the groups of eight, with and without photometric terms.
#[test]
fn lanes_accumulate_as_the_scalar_pass() {
    if !solve::has_avx2_fma() {
        eprintln!("skipped: this CPU has no AVX2/FMA");
        return;
    }
    let k = Intrinsics {
        width: 331,
        height: 243,
        cx: 165.0,
        cy: 121.0,
        ..intrinsics()
    };
    let cfg = TrackerConfig {
        finest_level: 0,
        levels: 4,
        ..TrackerConfig::default()
    };
    let mut rng = crate::rng::Rng::new(7);
    let mut checked = 0;
    for (i, xi) in [
        [0.0; 6],
        [0.02, -0.01, 0.03, 0.01, -0.02, 0.015],
        [0.3, 0.1, -0.2, 0.05, 0.2, -0.1],
    ]
    .iter()
    .enumerate()
    {
        let t_wr = pose_of([0.01, 0.0, 0.0, 0.0, 0.01, 0.0]);
        let t_wf = t_wr * pose_of(*xi);
        let (rgb_r, mut d_r) = render(&t_wr, &k);
        let (rgb_f, mut d_f) = render(&t_wf, &k);
        // Holes, and depths out of range.
        for d in d_r.iter_mut().chain(d_f.iter_mut()) {
            let u = rng.next_f64();
            if u < 0.05 {
                *d = 0.0;
            } else if u < 0.06 {
                *d = 50.0;
            }
        }
        let r = Reference::new(Color::RgbF32(&rgb_r), &d_r, &k, &t_wr, &cfg).unwrap();
        let f = Frame::new(Color::RgbF32(&rgb_f), &d_f, &k, &cfg).unwrap();
        let (rot, t) = to_f32(&(se3::inverse(&t_wr) * t_wf));
        for l in 0..cfg.levels {
            let rl = RefLevel {
                lev: &r.frame.levels[l],
                igd: &r.igd[l],
                normals: &r.normals[l],
            };
            let base = Params::new(&cfg);
            let variants = [
                base,
                Params {
                    photo_weight: 0.0,
                    ..base
                },
                Params {
                    gain: 1.1,
                    min_grad_sq: 1e-4,
                    ..base
                },
            ];
            for p in variants {
                let a = solve::accumulate_with(&rl, &f.levels[l], &rot, &t, &p, false);
                let b = solve::accumulate_with(&rl, &f.levels[l], &rot, &t, &p, true);
                let what = format!("pose {i}, level {l}, {p:?}");
                assert_eq!(
                    (a.n_valid, a.n_geo, a.n_photo, a.n_inlier),
                    (b.n_valid, b.n_geo, b.n_photo, b.n_inlier),
                    "{what}"
                );
                let scale = a.h.iter().fold(1e-12f64, |m, v| m.max(v.abs()));
                for (x, y) in a.h.iter().zip(&b.h) {
                    assert!((x - y).abs() <= 1e-5 * scale, "H {x} vs {y}, {what}");
                }
                let bs = a.b.iter().fold(1e-12f64, |m, v| m.max(v.abs()));
                for (x, y) in a.b.iter().zip(&b.b) {
                    assert!(
                        (x - y).abs() <= 1e-5 * bs.max(1e-6 * scale),
                        "b {x} vs {y}, {what}"
                    );
                }
                for (x, y, name) in [
                    (a.cost, b.cost, "cost"),
                    (a.sq_geo, b.sq_geo, "sq_geo"),
                    (a.sq_photo, b.sq_photo, "sq_photo"),
                    (a.depth_sum, b.depth_sum, "depth_sum"),
                    (a.sum_ir, b.sum_ir, "sum_ir"),
                    (a.sum_if, b.sum_if, "sum_if"),
                ] {
                    assert!(
                        (x - y).abs() <= 1e-5 * x.abs().max(1e-9),
                        "{name} {x} vs {y}, {what}"
                    );
                }
                checked += usize::from(a.n_geo > 0 && a.n_photo > 0);
            }
        }
    }
    // Most cases had both kinds of terms (the large motion leaves some levels with few).
    assert!(checked >= 18, "{checked} cases with terms");
}

#[test]
#[ignore]
fn track_timing_breakdown() {
    use std::time::Instant;
    let k = Intrinsics {
        fx: 585.0,
        fy: 585.0,
        cx: 319.5,
        cy: 239.5,
        width: 640,
        height: 480,
    };
    let cfg = TrackerConfig::default();
    let t_wr = pose_of([0.0; 6]);
    let t_wf = pose_of([0.01, 0.0, 0.01, 0.0, 0.01, 0.0]);
    let (rgb_r, d_r) = render(&t_wr, &k);
    let (rgb_f, d_f) = render(&t_wf, &k);
    let rgb8: Vec<u8> = rgb_f.iter().map(|v| (v * 255.0) as u8).collect();
    let n = 100;
    let time = |name: &str, f: &mut dyn FnMut()| {
        let (t0, c0) = (Instant::now(), cpu_ms());
        for _ in 0..n {
            f();
        }
        let wall = t0.elapsed().as_secs_f64() * 1e3 / n as f64;
        let cpu = (cpu_ms() - c0) / n as f64;
        println!("{name:<28} wall {wall:7.3} ms   cpu {cpu:7.3} ms");
    };
    let f = Frame::new(Color::Rgb8(&rgb8), &d_f, &k, &cfg).unwrap();
    let r0 = Frame::new(Color::RgbF32(&rgb_r), &d_r, &k, &cfg).unwrap();
    let r = Reference::from_frame(r0.clone(), &t_wr, &cfg).unwrap();
    time("frame prep", &mut || {
        std::hint::black_box(Frame::new(Color::Rgb8(&rgb8), &d_f, &k, &cfg).unwrap());
    });
    time("clone frame", &mut || {
        std::hint::black_box(r0.clone());
    });
    time("reference prep (+clone)", &mut || {
        std::hint::black_box(Reference::from_frame(r0.clone(), &t_wr, &cfg).unwrap());
    });
    let p = Params::new(&cfg);
    let (rot, t) = to_f32(&(se3::inverse(&t_wr) * t_wf));
    for l in 0..4 {
        let rl = RefLevel {
            lev: &r.frame.levels[l],
            igd: &r.igd[l],
            normals: &r.normals[l],
        };
        if rl.igd.is_empty() {
            continue;
        }
        time(&format!("accumulate level {l}"), &mut || {
            std::hint::black_box(solve::accumulate(&rl, &f.levels[l], &rot, &t, &p));
        });
        let pg = Params {
            photo_weight: 0.0,
            ..p
        };
        time(&format!("  geometric only {l}"), &mut || {
            std::hint::black_box(solve::accumulate(&rl, &f.levels[l], &rot, &t, &pg));
        });
    }
    time("track", &mut || {
        std::hint::black_box(track(&r, &f, &t_wr, &cfg).unwrap());
    });
}
