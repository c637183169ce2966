//! The fused surface volume against analytic scenes: what it ray-casts is the surface it was
//! shown, from views it was not built from; fusing averages noise; the block-skipping march
//! finds what a plain fine-stepped march finds; any thread count gives the same bits.

use legslam_core::camera::{se3, Intrinsics, Pose};
use legslam_core::rng::Rng;
use legslam_core::track::{Tsdf, TsdfConfig};
use nalgebra::{Vector3, Vector6};

const W: usize = 80;
const H: usize = 60;

fn intrinsics() -> Intrinsics {
    Intrinsics::from_array([70.0, 72.0, 39.5, 29.5], W, H)
}

/// Planes `n . p = d` (unit n) and spheres (centre, radius), around and across the origin (so
/// that blocks of negative coordinates are exercised).
struct Scene {
    planes: Vec<(Vector3<f64>, f64)>,
    spheres: Vec<(Vector3<f64>, f64)>,
}

impl Scene {
    fn room(rng: &mut Rng, spheres: usize) -> Scene {
        let planes = vec![
            (Vector3::new(0.0, 0.0, 1.0), 2.2),
            (Vector3::new(0.0, 1.0, 0.0), 0.6),
            (Vector3::new(1.0, 0.0, 0.0).normalize(), 1.1),
        ];
        let spheres = (0..spheres)
            .map(|_| {
                let c = Vector3::new(
                    rng.uniform(-0.6, 0.6),
                    rng.uniform(-0.4, 0.3),
                    rng.uniform(1.2, 1.9),
                );
                (c, rng.uniform(0.08, 0.25))
            })
            .collect();
        Scene { planes, spheres }
    }

    /// Depth (camera z) of the nearest surface through each pixel; 0 where none is in range.
    fn depth(&self, k: &Intrinsics, pose: &Pose) -> Vec<f32> {
        let r = se3::rotation(pose);
        let o = se3::translation(pose);
        let mut out = vec![0.0; k.width * k.height];
        for v in 0..k.height {
            for u in 0..k.width {
                let d = r * Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
                let mut best = f64::INFINITY;
                for (n, dist) in &self.planes {
                    let dn = n.dot(&d);
                    if dn.abs() > 1e-9 {
                        let t = (dist - n.dot(&o)) / dn;
                        if t > 0.0 {
                            best = best.min(t);
                        }
                    }
                }
                for (c, rad) in &self.spheres {
                    // |o + t d - c|^2 = rad^2
                    let oc = o - c;
                    let (a, b, cc) = (d.dot(&d), 2.0 * d.dot(&oc), oc.dot(&oc) - rad * rad);
                    let disc = b * b - 4.0 * a * cc;
                    if disc >= 0.0 {
                        let t = (-b - disc.sqrt()) / (2.0 * a);
                        if t > 0.0 {
                            best = best.min(t);
                        }
                    }
                }
                if best.is_finite() && best <= 4.0 {
                    out[v * k.width + u] = best as f32;
                }
            }
        }
        out
    }
}

/// A camera near the origin looking roughly along +z.
fn pose(rng: &mut Rng, spread: f64) -> Pose {
    let xi = Vector6::from_iterator((0..6).map(|i| {
        let s = if i < 3 { 0.15 } else { 0.12 };
        rng.uniform(-s, s) * spread
    }));
    se3::exp(&xi)
}

fn config() -> TsdfConfig {
    TsdfConfig {
        voxel: 0.02,
        truncation: 0.08,
        max_depth: 4.0,
        ..TsdfConfig::default()
    }
}

fn fused(scene: &Scene, poses: &[Pose], noise: f64, rng: &mut Rng) -> Tsdf {
    let mut tsdf = Tsdf::new(config()).unwrap();
    for p in poses {
        let mut d = scene.depth(&intrinsics(), p);
        for v in d.iter_mut().filter(|v| **v > 0.0) {
            *v += (noise * rng.normal()) as f32;
        }
        tsdf.integrate(&d, &intrinsics(), p).unwrap();
    }
    tsdf
}

/// A room with `spheres` spheres, fused from `views` random views (spread 1) with depth noise
/// `noise` (m).
fn fused_room(rng: &mut Rng, spheres: usize, views: usize, noise: f64) -> (Scene, Tsdf) {
    let scene = Scene::room(rng, spheres);
    let poses: Vec<Pose> = (0..views).map(|_| pose(rng, 1.0)).collect();
    let tsdf = fused(&scene, &poses, noise, rng);
    (scene, tsdf)
}

fn cast(tsdf: &Tsdf, p: &Pose) -> Vec<f32> {
    let mut out = vec![0.0; W * H];
    tsdf.raycast(&intrinsics(), p, &mut out).unwrap();
    out
}

/// Pixels where both see a surface, how many of the truth's surface pixels the cast misses,
/// and the errors' median and 95th percentile (m) over the pixels both see.
fn compare(cast: &[f32], truth: &[f32]) -> (usize, usize, f64, f64) {
    let mut errs: Vec<f64> = Vec::new();
    let mut missed = 0;
    for (&c, &t) in cast.iter().zip(truth) {
        if t > 0.0 && c > 0.0 {
            errs.push((c - t).abs() as f64);
        } else if t > 0.0 {
            missed += 1;
        }
    }
    errs.sort_by(f64::total_cmp);
    let q = |f: f64| errs[((errs.len() - 1) as f64 * f) as usize];
    (errs.len(), missed, q(0.5), q(0.95))
}

#[test]
fn a_view_it_was_not_built_from_sees_the_true_surface() {
    let mut rng = Rng::new(3);
    let (scene, tsdf) = fused_room(&mut rng, 4, 6, 0.0);
    for _ in 0..3 {
        let p = pose(&mut rng, 0.5);
        let (n, missed, med, p95) = compare(&cast(&tsdf, &p), &scene.depth(&intrinsics(), &p));
        assert!(n > W * H * 9 / 10, "only {n} pixels hit");
        assert!(missed < W * H / 50, "{missed} surface pixels missed");
        assert!(
            med < 0.002 && p95 < 0.01,
            "error median {med} m, 95% {p95} m"
        );
    }
}

#[test]
fn fusing_noisy_frames_averages_the_noise() {
    let mut rng = Rng::new(5);
    let scene = Scene::room(&mut rng, 0);
    let poses: Vec<Pose> = (0..30).map(|_| pose(&mut rng, 0.3)).collect();
    let noise = 0.01;
    let one = fused(&scene, &poses[..1], noise, &mut rng);
    let all = fused(&scene, &poses, noise, &mut rng);
    let p = poses[0];
    let truth = scene.depth(&intrinsics(), &p);
    let (_, _, med1, _) = compare(&cast(&one, &p), &truth);
    let (n, _, med, p95) = compare(&cast(&all, &p), &truth);
    assert!(n > W * H * 9 / 10, "only {n} pixels hit");
    assert!(
        med < 0.3 * med1,
        "fused median error {med} m against one frame's {med1} m"
    );
    assert!(p95 < 0.006, "fused 95% error {p95} m");
}

/// The plain reference: marches over every sample a voxel apart through the voxels' distances
/// to the first crossing from in front of a surface to behind it, and interpolates between the
/// trilinear distances (the voxels' where undefined) of its two samples.
fn plain_march(tsdf: &Tsdf, k: &Intrinsics, p: &Pose, u: usize, v: usize) -> f32 {
    let r = se3::rotation(p);
    let o = se3::translation(p);
    let d = r * Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
    let point = |t: f64| {
        let x = o + t * d;
        [x.x, x.y, x.z]
    };
    let cfg = tsdf.config();
    let step = cfg.voxel / d.norm();
    let mut prev: Option<(f64, f64)> = None;
    let mut n = 0;
    loop {
        let t = cfg.min_depth + n as f64 * step;
        if t > cfg.max_depth {
            return 0.0;
        }
        match tsdf.voxel_distance(point(t)) {
            Some(f) if f > 0.0 => prev = Some((t, f)),
            Some(f) => match prev {
                Some((tp, fp)) => {
                    let fp = tsdf.distance(point(tp)).unwrap_or(fp);
                    let f = tsdf.distance(point(t)).unwrap_or(f);
                    let ts = if fp > f {
                        tp + (t - tp) * fp / (fp - f)
                    } else {
                        t
                    };
                    return ts.clamp(tp, t) as f32;
                }
                None if f < 0.0 => return 0.0,
                None => {}
            },
            None => prev = None,
        }
        n += 1;
    }
}

#[test]
fn the_block_skipping_march_finds_what_a_plain_march_finds() {
    let mut rng = Rng::new(11);
    for _ in 0..3 {
        let (_, tsdf) = fused_room(&mut rng, 6, 4, 0.003);
        let p = pose(&mut rng, 1.0);
        let fast = cast(&tsdf, &p);
        let k = intrinsics();
        let mut agree = 0;
        let mut disagree = Vec::new();
        for v in 0..H {
            for u in 0..W {
                let (a, b) = (fast[v * W + u], plain_march(&tsdf, &k, &p, u, v));
                if (a > 0.0) == (b > 0.0) && (a - b).abs() < 0.005 {
                    agree += 1;
                } else {
                    disagree.push((u, v, a, b));
                }
            }
        }
        // One finding a surface where the other finds none: rarer still.
        let hit_or_miss = disagree
            .iter()
            .filter(|d| (d.2 > 0.0) != (d.3 > 0.0))
            .count();
        assert!(hit_or_miss <= W * H / 200, "{hit_or_miss} hit or miss");
        assert!(
            agree >= W * H * 99 / 100,
            "{} pixels differ, e.g. {:?}",
            disagree.len(),
            &disagree[..disagree.len().min(5)]
        );
    }
}

#[test]
fn a_march_begun_near_the_measured_depth_finds_the_same_surface() {
    let mut rng = Rng::new(19);
    let (scene, tsdf) = fused_room(&mut rng, 6, 5, 0.004);
    let p = pose(&mut rng, 0.5);
    let k = intrinsics();
    let full = cast(&tsdf, &p);
    // Measured depth a little off the truth, with holes; and one far in front of the surface.
    let mut near = scene.depth(&k, &p);
    for (i, v) in near.iter_mut().enumerate() {
        *v = match i % 7 {
            0 => 0.0,
            1 => 0.3,
            _ => *v + (0.01 * rng.normal()) as f32,
        };
    }
    let ok = near.iter().filter(|&&d| d > 0.0);
    let lo = ok.clone().fold(f32::INFINITY, |a, &b| a.min(b));
    let hi = ok.fold(0.0f32, |a, &b| a.max(b));
    let mut from_near = vec![0.0; W * H];
    tsdf.raycast_near(&k, &p, &near, 1, &mut from_near).unwrap();
    // Where the march skips ahead it may step over a sliver of noise that a march begun
    // elsewhere lands in: compared as the plain march is, not bit for bit.
    let (mut compared, mut agree) = (0, 0);
    for i in 0..W * H {
        let (a, b) = (full[i], from_near[i]);
        match i % 7 {
            // No measurement: the ray covers the measured depths only.
            0 => {
                assert!(
                    b == 0.0 || (b >= lo - 0.16 && b <= hi + 0.16),
                    "pixel {i}: {b}"
                );
                if a > lo - 0.1 && a < hi + 0.1 {
                    compared += 1;
                    agree += ((a - b).abs() < 0.005) as usize;
                }
            }
            // Begun where the wall's band is far behind: nothing in front of where it began.
            1 => assert!(b == 0.0 || b >= 0.3 - 2.0 * 0.08, "pixel {i}: {b}"),
            _ if a > 0.0 && (a - near[i]).abs() < 0.08 => {
                compared += 1;
                agree += ((a - b).abs() < 0.005) as usize;
            }
            _ => {}
        }
    }
    assert!(compared > W * H / 2, "only {compared} pixels compared");
    assert!(agree >= compared * 98 / 100, "{agree} of {compared} agree");
    let err = tsdf
        .raycast_near(&k, &p, &near[1..], 1, &mut from_near)
        .unwrap_err();
    assert!(err.contains("near has"), "{err}");
}

#[test]
fn holes_cast_in_cells_see_the_surface_through_the_cell_centres() {
    let mut rng = Rng::new(23);
    let (scene, tsdf) = fused_room(&mut rng, 6, 5, 0.0);
    let p = pose(&mut rng, 0.5);
    let k = intrinsics();
    // An empty border (a registered depth image's) and scattered holes.
    let mut near = scene.depth(&k, &p);
    for (i, d) in near.iter_mut().enumerate() {
        let (u, v) = (i % W, i / W);
        if u < 24 || v < 12 || i % 5 == 0 {
            *d = 0.0;
        }
    }
    let mut single = vec![0.0; W * H];
    tsdf.raycast_near(&k, &p, &near, 1, &mut single).unwrap();
    let cell = 4;
    let mut cells = vec![0.0; W * H];
    tsdf.raycast_near(&k, &p, &near, cell, &mut cells).unwrap();
    // The surface through each cell's centre: a camera whose pixels are the cells.
    let c = cell as f64;
    let k_cells = Intrinsics::from_array(
        [
            k.fx / c,
            k.fy / c,
            (k.cx - 0.5 * (c - 1.0)) / c,
            (k.cy - 0.5 * (c - 1.0)) / c,
        ],
        W / cell,
        H / cell,
    );
    let truth_cells = scene.depth(&k_cells, &p);
    let (mut cast, mut truth) = (Vec::new(), Vec::new());
    for i in 0..W * H {
        if near[i] > 0.0 {
            assert_eq!(
                cells[i].to_bits(),
                single[i].to_bits(),
                "measured pixel {i}"
            );
        } else {
            let (u, v) = (i % W, i / W);
            cast.push(cells[i]);
            truth.push(truth_cells[(v / cell) * (W / cell) + u / cell]);
        }
    }
    let (seen, missed, median, p95) = compare(&cast, &truth);
    assert!(
        seen > cast.len() / 2,
        "{seen} of {} holes see a surface",
        cast.len()
    );
    assert!(missed * 50 < seen, "{missed} missed");
    assert!(median < 0.004 && p95 < 0.02, "median {median}, 95% {p95}");
    // Cells cut by the image's edge; no cell at all is refused.
    let mut odd = vec![0.0; W * H];
    tsdf.raycast_near(&k, &p, &near, 7, &mut odd).unwrap();
    assert!(near
        .iter()
        .zip(&odd)
        .zip(&single)
        .all(|((&n, a), b)| n == 0.0 || a == b));
    assert!(odd.iter().filter(|&&d| d > 0.0).count() > W * H / 2);
    let err = tsdf.raycast_near(&k, &p, &near, 0, &mut odd).unwrap_err();
    assert!(err.contains("hole_cell"), "{err}");
}

#[test]
fn any_thread_count_gives_the_same_bits() {
    let mut rng = Rng::new(13);
    let scene = Scene::room(&mut rng, 5);
    let poses: Vec<Pose> = (0..4).map(|_| pose(&mut rng, 1.0)).collect();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let tsdf = fused(&scene, &poses, 0.005, &mut Rng::new(1));
            let d = cast(&tsdf, &poses[1]);
            (tsdf.blocks(), d)
        })
    };
    let (b1, d1) = run(1);
    let (b3, d3) = run(3);
    assert_eq!(b1, b3);
    assert!(d1.iter().zip(&d3).all(|(a, b)| a.to_bits() == b.to_bits()));
    assert!(d1.iter().filter(|v| **v > 0.0).count() > W * H / 2);
}

#[test]
fn bad_input_is_refused_and_missing_depth_is_ignored() {
    let k = intrinsics();
    let mut tsdf = Tsdf::new(config()).unwrap();
    let eye = Pose::identity();
    let err = tsdf.integrate(&vec![1.0; W * H - 1], &k, &eye).unwrap_err();
    assert!(err.contains("4799 values"), "{err}");
    let mut nan_pose = eye;
    nan_pose[(0, 3)] = f64::NAN;
    assert!(tsdf.integrate(&vec![1.0; W * H], &k, &nan_pose).is_err());
    assert!(tsdf.raycast(&k, &eye, &mut [0.0; 3]).is_err());
    for bad in [
        TsdfConfig {
            voxel: 0.0,
            ..config()
        },
        TsdfConfig {
            truncation: 0.01,
            ..config()
        },
        TsdfConfig {
            max_weight: f32::NAN,
            ..config()
        },
        TsdfConfig {
            max_weight: 256.0,
            ..config()
        },
        TsdfConfig {
            max_weight: 2.5,
            ..config()
        },
        TsdfConfig {
            min_depth: 5.0,
            ..config()
        },
    ] {
        assert!(Tsdf::new(bad).is_err(), "{bad:?} accepted");
    }
    // NaN, infinite, zero and negative depth add nothing, with a zero minimum depth too.
    let junk = [f32::NAN, f32::INFINITY, 0.0, -1.0];
    let d: Vec<f32> = (0..W * H).map(|i| junk[i % 4]).collect();
    tsdf.integrate(&d, &k, &eye).unwrap();
    assert_eq!(tsdf.blocks(), 0);
    let mut from_zero = Tsdf::new(TsdfConfig {
        min_depth: 0.0,
        ..config()
    })
    .unwrap();
    from_zero.integrate(&d, &k, &eye).unwrap();
    assert_eq!(from_zero.blocks(), 0);
    // Nothing fused: nothing seen.
    assert!(cast(&tsdf, &eye).iter().all(|v| *v == 0.0));
}

#[test]
fn a_surface_seen_from_behind_is_not_a_surface() {
    let mut rng = Rng::new(17);
    let scene = Scene {
        planes: vec![(Vector3::new(0.0, 0.0, 1.0), 1.5)],
        spheres: vec![],
    };
    let tsdf = fused(&scene, &[Pose::identity()], 0.0, &mut rng);
    assert!(tsdf.blocks() > 0);
    // Turned round and standing beyond the wall, looking back at it.
    let mut behind = se3::exp(&Vector6::new(0.0, 0.0, 0.0, 0.0, std::f64::consts::PI, 0.0));
    behind[(2, 3)] = 2.5;
    assert!(cast(&tsdf, &behind).iter().all(|v| *v == 0.0));
    // Looking away from it, from in front.
    let mut away = behind;
    away[(2, 3)] = 0.5;
    assert!(cast(&tsdf, &away).iter().all(|v| *v == 0.0));
}
