//! The mapper end to end on a textured wall: training lowers the loss, densification and
//! pruning keep the optimiser's rows in step with the map's.

use legslam_core::camera::{Intrinsics, Pose};
use legslam_core::map::order::spatial_order;
use legslam_core::map::{GaussianMap, Mapper, MapperConfig};
use legslam_core::optim::Groups;
use legslam_core::Real;

fn wall(w: usize, h: usize) -> (Vec<Real>, Vec<Real>, Intrinsics) {
    let mut rgb = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let check = ((x / 6 + y / 6) % 2) as Real;
            rgb.extend([0.2 + 0.6 * check, 0.3 + 0.4 * (x as Real / w as Real), 0.5]);
        }
    }
    let depth = (0..w * h).map(|p| 2.0 + 0.002 * (p % w) as Real).collect();
    let k = Intrinsics {
        fx: 60.0,
        fy: 60.0,
        cx: (w as f64 - 1.0) / 2.0,
        cy: (h as f64 - 1.0) / 2.0,
        width: w,
        height: h,
    };
    (rgb, depth, k)
}

#[test]
fn training_lowers_the_loss_and_refinement_keeps_rows_in_step() {
    let mut cfg = MapperConfig {
        finest_level: 0,
        grow_level: 1,
        ..Default::default()
    };
    cfg.densify.interval = 15;
    cfg.densify.grad_threshold = 1e-9; // densify eagerly: exercises clone/split bookkeeping
    cfg.densify.max_gaussians = 3000;
    let mut m = Mapper::new(cfg).unwrap();
    let (rgb, depth, k) = wall(64, 48);
    let (_, added) = m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
    assert_eq!(added, 32 * 24);
    let first = m.train(1).unwrap().last.total;
    let report = m.train(60).unwrap();
    assert!(report.cloned + report.split > 0, "{report:?}");
    assert!(m.map.len() <= 3000);
    assert!(
        report.last.total < 0.7 * first,
        "loss {first} -> {}",
        report.last.total
    );
    // A second, overlapping keyframe adds little: the map already explains its depth.
    let (rgb, depth, k) = wall(64, 48);
    let (_, more) = m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
    assert!(
        more < added / 4,
        "{more} new Gaussians for a view already mapped"
    );
    m.train(5).unwrap();
}

/// A keyframe trains `uses_per_level` times at each level from the coarsest down, then stays at
/// `finest_level` (what the mapper bench waits for before it times iterations).
#[test]
fn each_keyframe_trains_coarse_to_fine() {
    let cfg = MapperConfig {
        levels: 3,
        finest_level: 1,
        uses_per_level: 2,
        grow_level: 1,
        ..Default::default()
    };
    let mut m = Mapper::new(cfg).unwrap();
    let (rgb, depth, k) = wall(64, 48);
    m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
    let mut levels = Vec::new();
    for _ in 0..6 {
        levels.push(m.training_level(0));
        m.train(1).unwrap();
    }
    assert_eq!(levels, [2, 2, 1, 1, 1, 1]);
    assert_eq!(m.keyframes[0].uses, 6);
}

#[test]
fn mapper_options_by_name_reach_their_fields_and_keep_their_kinds() {
    use legslam_core::options::{Options, Value};

    let mut c = MapperConfig::default();
    c.set("window", Value::Int(4)).unwrap();
    c.set("lr_sh", Value::Real(0.01)).unwrap();
    c.set("adam_sparse", Value::Bool(true)).unwrap();
    assert!(c.adam.sparse_features && c.adam.sparse_sh, "SLAM's default");
    c.set("adam_sparse_features", Value::Bool(false)).unwrap();
    c.set("adam_sparse_sh", Value::Bool(false)).unwrap();
    assert_eq!(c.window, 4);
    assert!((c.adam.lr.sh - 0.01).abs() < 1e-9 && c.adam.sparse && !c.adam.sparse_features);
    assert!(!c.adam.sparse_sh);
    assert!(c.spatial_order, "on by default");
    c.set("spatial_order", Value::Bool(false)).unwrap();
    assert!(!c.spatial_order);
    let entries = c.entries();
    assert!(entries.contains(&("window", Value::Int(4))));
    assert!(entries.contains(&("adam_sparse", Value::Bool(true))));
    let unknown = c.set("windw", Value::Int(1)).unwrap_err();
    assert!(unknown.contains("unknown mapper option"), "{unknown}");
    assert!(c.set("window", Value::Real(2.5)).is_err());
    assert!(
        c.set("adam_sparse", Value::Int(1)).is_err(),
        "a flag is a bool"
    );
    c.set("lr_sh", Value::Real(f64::NAN)).unwrap();
    let nan = c.validate().unwrap_err();
    assert!(nan.contains("lr_sh must be finite"), "{nan}");
}

#[test]
fn growth_from_keyframes_respects_the_cap() {
    let mut cfg = MapperConfig {
        finest_level: 0,
        grow_level: 0,
        ..Default::default()
    };
    cfg.densify.max_gaussians = 1000;
    let mut m = Mapper::new(cfg).unwrap();
    let (rgb, depth, k) = wall(64, 48);
    let (_, added) = m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
    assert_eq!(added, 1000);
    assert_eq!(m.map.len(), 1000);
    // kept rows are spread over the whole view, not its top rows only
    let ys: Vec<Real> = m.map.means.chunks(3).map(|p| p[1]).collect();
    let (lo, hi) = ys
        .iter()
        .fold((Real::MAX, Real::MIN), |(a, b), y| (a.min(*y), b.max(*y)));
    assert!(lo < -0.6 && hi > 0.6, "{lo} {hi}");
    m.train(3).unwrap();
}

/// Features trained one or two pyramid levels below the colour, each coarse pixel the render of
/// its block or a point drawn in it afresh each iteration, still learn a two-region target:
/// the full-resolution render ends up close to it, on both sides of the boundary.
#[test]
fn features_trained_at_a_coarser_level_learn_the_target() {
    use legslam_core::map::FeatureGrid;
    for (offset, jitter) in [(0, false), (1, false), (2, false), (1, true), (2, true)] {
        let mut cfg = MapperConfig {
            finest_level: 0,
            grow_level: 0,
            num_features: 4,
            feature_level_offset: offset,
            feature_jitter: jitter,
            ..Default::default()
        };
        cfg.densify.interval = 0;
        cfg.adam.lr.features = 0.02;
        let mut m = Mapper::new(cfg).unwrap();
        let (rgb, depth, k) = wall(64, 48);
        let (id, _) = m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
        // 8x6 grid: left half (1,0,0,0), right half (0,1,0,0)
        let data: Vec<Real> = (0..48)
            .flat_map(|c| {
                if c % 8 < 4 {
                    [1.0, 0.0, 0.0, 0.0]
                } else {
                    [0.0, 1.0, 0.0, 0.0]
                }
            })
            .collect();
        let grid = FeatureGrid::new(data, 8, 6, 4).unwrap();
        let target = grid.upsample(64, 48);
        m.set_features(id, grid).unwrap();
        // start from features unrelated to the target
        m.map
            .features
            .iter_mut()
            .enumerate()
            .for_each(|(i, f)| *f = [0.3, 0.3, 0.6, 0.5][i % 4]);
        let first = m.train(1).unwrap().last.feature;
        let last = m.train(80).unwrap().last.feature;
        assert!(
            first > 0.2 && last < 0.25 * first,
            "offset {offset}, jitter {jitter}: {first} -> {last}"
        );
        let r = m.render(&Pose::identity(), k, true, true).unwrap();
        for (x, y) in [(8, 24), (56, 24)] {
            let p = y * 64 + x;
            let (a, b) = (&r.features[p * 4..][..4], &target[p * 4..][..4]);
            let dot: Real = a.iter().zip(b).map(|(u, v)| u * v).sum();
            let na: Real = a.iter().map(|u| u * u).sum::<Real>().sqrt();
            assert!(
                dot / na > 0.9,
                "offset {offset}, jitter {jitter} at ({x},{y}): {a:?} vs {b:?}"
            );
        }
    }
}

/// Features point-sampled two levels below the colour learn stripes two coarse pixels wide only
/// where the target is sampled at the points the render is: the full-resolution render ends up
/// close to the full-resolution target across the stripes' edges.
#[test]
fn point_sampled_features_learn_the_target_where_they_sample_it() {
    use legslam_core::map::FeatureGrid;
    let (w, h) = (64, 48);
    let mut cfg = MapperConfig {
        finest_level: 0,
        grow_level: 0,
        num_features: 2,
        feature_level_offset: 2,
        feature_jitter: true,
        ..Default::default()
    };
    cfg.densify.interval = 0;
    cfg.adam.lr.features = 0.02;
    let mut m = Mapper::new(cfg).unwrap();
    let (rgb, depth, k) = wall(w, h);
    let (id, _) = m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
    // Vertical stripes, one 8-pixel (two-coarse-pixel) grid cell wide each.
    let (gw, gh) = (w / 8, h / 8);
    let data: Vec<Real> = (0..gw * gh)
        .flat_map(|c| if c % 2 == 0 { [1.0, 0.0] } else { [0.0, 1.0] })
        .collect();
    let grid = FeatureGrid::new(data, gw, gh, 2).unwrap();
    let target = grid.upsample(w, h);
    m.set_features(id, grid).unwrap();
    m.map.features.iter_mut().for_each(|f| *f = 0.5);
    m.train(150).unwrap();
    let r = m.render(&Pose::identity(), k, true, true).unwrap();
    let err: Real = (r.features.iter().zip(&target))
        .map(|(a, b)| (a - b).abs())
        .sum::<Real>()
        / target.len() as Real;
    // 0.04 here; 0.12 with the target sampled at the blocks' centres instead, 0.31 with each
    // coarse pixel the render of its block (`feature_jitter` false).
    assert!(err < 0.06, "mean error {err}");
}

/// `train` draws from the configured window of recent keyframes, `train_window` from the one
/// it is given, each a shuffled pass that visits every keyframe in it once.
#[test]
fn training_windows_choose_which_keyframes_are_trained() {
    let cfg = MapperConfig {
        finest_level: 0,
        grow_level: 1,
        window: 1,
        revisit: 0.0,
        ..Default::default()
    };
    let mut m = Mapper::new(cfg).unwrap();
    for _ in 0..3 {
        let (rgb, depth, k) = wall(32, 24);
        m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
    }
    let uses = |m: &Mapper| m.keyframes.iter().map(|k| k.uses).collect::<Vec<_>>();
    m.train(2).unwrap();
    assert_eq!(uses(&m), [0, 0, 2]);
    m.train_window(6, usize::MAX).unwrap();
    assert_eq!(uses(&m), [2, 2, 4]);
    assert_eq!(m.train_window(3, 0).unwrap().iterations, 0);
}

/// Pose refinement: a keyframe placed 4 cm and 1.5 degrees off the view it shows is pulled
/// back onto it by mapping it together with a keyframe of that view at the right pose, which
/// never moves itself (it anchors the map).
#[test]
fn keyframe_poses_are_refined_towards_the_view_they_show() {
    use legslam_core::camera::se3;
    use nalgebra::Vector6;

    let mut cfg = MapperConfig {
        finest_level: 0,
        grow_level: 0,
        pose_lr_translation: 2e-3,
        pose_lr_rotation: 2e-3,
        ..Default::default()
    };
    cfg.densify.interval = 0;
    let mut m = Mapper::new(cfg).unwrap();
    let (rgb, depth, k) = wall(64, 48);
    m.add_keyframe(rgb.clone(), depth.clone(), k, Pose::identity())
        .unwrap();
    // A map that reproduces the view first (freshly grown splats render it a little shifted).
    m.train(200).unwrap();
    let off = se3::exp(&Vector6::new(0.04, -0.02, 0.0, 0.0, 0.0, 0.026));
    m.config.grow.alpha_threshold = 0.0; // the second keyframe adds no Gaussians
    m.config.grow.depth_tolerance = 1e9;
    m.config.grow.occluded_tolerance = 1e9;
    let (_, added) = m.add_keyframe(rgb, depth, k, off).unwrap();
    assert_eq!(added, 0);
    let error = |m: &Mapper, i: usize| {
        let e = se3::log(&m.keyframes[i].pose);
        (e.fixed_rows::<3>(0).norm(), e.fixed_rows::<3>(3).norm())
    };
    let (t0, r0) = error(&m, 1);
    m.train_window(300, 2).unwrap();
    let (t1, r1) = error(&m, 1);
    assert!(
        t1 < 0.25 * t0 && r1 < 0.25 * r0,
        "translation {t0} -> {t1}, rotation {r0} -> {r1}"
    );
    assert_eq!(
        m.keyframes[0].pose,
        Pose::identity(),
        "the first keyframe moved"
    );
    assert_eq!(m.keyframes[0].pose_adam.steps(), 0);
    assert!(m.keyframes[1].pose_adam.steps() > 100);
}

/// `revisit`: that share of iterations trains a keyframe older than the window, drawn
/// uniformly; the rest stay in the window.
#[test]
fn a_share_of_iterations_revisits_older_keyframes() {
    let cfg = MapperConfig {
        finest_level: 0,
        grow_level: 1,
        window: 1,
        revisit: 0.5,
        ..Default::default()
    };
    let mut m = Mapper::new(cfg).unwrap();
    for _ in 0..4 {
        let (rgb, depth, k) = wall(32, 24);
        m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
    }
    m.train(80).unwrap();
    let uses: Vec<usize> = m.keyframes.iter().map(|k| k.uses).collect();
    let older: usize = uses[..3].iter().sum();
    assert!((25..=55).contains(&older), "{uses:?}");
    assert!(uses[..3].iter().all(|&u| u > 3), "{uses:?}");
    let bad = MapperConfig {
        revisit: 1.5,
        ..Default::default()
    };
    assert!(Mapper::new(bad).err().unwrap().contains("revisit"));
}

/// How many Gaussians lie beyond `z` (the camera looks along +z from the origin).
fn beyond(m: &Mapper, z: Real) -> usize {
    m.map.means.chunks_exact(3).filter(|p| p[2] > z).count()
}

#[test]
fn gaussians_hidden_behind_a_nearer_surface_are_pruned_by_contribution() {
    // A far wall, then a nearer one in front of it at the same pose, trained alone: the far
    // wall's Gaussians end up behind an opaque surface in every view.
    let run = |min_contribution: Real| {
        let mut cfg = MapperConfig {
            finest_level: 0,
            grow_level: 1,
            window: 1,
            revisit: 0.0,
            ..Default::default()
        };
        cfg.densify.interval = 10;
        cfg.densify.grad_threshold = 1e9; // pruning alone
        cfg.prune.min_contribution = min_contribution;
        let mut m = Mapper::new(cfg).unwrap();
        let (rgb, depth, k) = wall(64, 48);
        let far: Vec<Real> = depth.iter().map(|d| d + 2.0).collect();
        m.add_keyframe(rgb.clone(), far, k, Pose::identity())
            .unwrap();
        m.train(20).unwrap();
        let hidden = beyond(&m, 3.0);
        let red: Vec<Real> = rgb.chunks_exact(3).flat_map(|_| [0.9, 0.1, 0.1]).collect();
        let (_, near) = m.add_keyframe(red, depth, k, Pose::identity()).unwrap();
        m.train(60).unwrap();
        // The loss on the near wall's view, once more without changing the map's shape.
        let loss = m.train(1).unwrap().last.total;
        (hidden, near, beyond(&m, 3.0), loss)
    };
    let (hidden, near, kept_off, loss_off) = run(0.0);
    assert!(hidden > 100 && near > 100, "{hidden} far, {near} near");
    // A quarter of one of the view's 64 x 48 pixels, in millionths of the view.
    let (_, _, kept_on, loss_on) = run(0.25 * 1e6 / (64.0 * 48.0));
    assert!(
        kept_off > hidden / 2,
        "without the rule: {kept_off} of {hidden} kept"
    );
    assert!(kept_on < hidden / 10, "with it: {kept_on} of {hidden} kept");
    // The rule also takes the near wall's most shadowed Gaussians (a few percent more loss
    // here); a threshold 4x higher left holes (12x the loss).
    assert!(
        loss_on < 1.3 * loss_off,
        "the visible wall's loss: {loss_on} with the rule, {loss_off} without"
    );
}

#[test]
fn keyframes_keep_only_the_levels_mapping_uses() {
    let cfg = MapperConfig {
        levels: 3,
        finest_level: 1,
        grow_level: 2,
        ..Default::default()
    };
    let mut m = Mapper::new(cfg).unwrap();
    let (rgb, depth, k) = wall(64, 48);
    let mut sorted = depth.clone();
    sorted.sort_by(|a, b| a.total_cmp(b));
    m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
    let levels = &m.keyframes[0].levels;
    assert!(levels[0].rgb.is_empty() && levels[0].depth.is_empty());
    assert_eq!(levels[0].intrinsics.width, 64);
    assert_eq!(
        (levels[1].rgb.len(), levels[1].depth.len()),
        (32 * 24 * 3, 32 * 24)
    );
    assert_eq!(levels[2].depth.len(), 16 * 12);
    // The scene extent still comes from the full-resolution depth.
    assert_eq!(m.extent(), sorted[sorted.len() / 2]);
    assert!(m.train(10).unwrap().last.total.is_finite());
    // Asked for a level it no longer has, training uses the finest it kept.
    m.config.finest_level = 0;
    assert!(m.train(5).unwrap().last.total.is_finite());

    // Training at full resolution keeps it.
    let mut full = Mapper::new(MapperConfig {
        finest_level: 0,
        ..Default::default()
    })
    .unwrap();
    let (rgb, depth, k) = wall(64, 48);
    full.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
    assert_eq!(full.keyframes[0].levels[0].depth.len(), 64 * 48);
}

/// One mapping iteration on a wall, with the learning rates `set` sets: the map before it and
/// the mapper after.
fn first_step(set: impl FnOnce(&mut Mapper)) -> (GaussianMap, Mapper) {
    let cfg = MapperConfig {
        finest_level: 0,
        grow_level: 1,
        ..Default::default()
    };
    let mut m = Mapper::new(cfg).unwrap();
    let (rgb, depth, k) = wall(32, 24);
    m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
    let before = m.map.clone();
    set(&mut m);
    m.train(1).unwrap();
    (before, m)
}

/// How far that step moved the means, log-scales, opacities and SH (sums of |change|).
fn step_sizes((before, m): &(GaussianMap, Mapper)) -> [f64; 4] {
    let sum = |a: &[Real], b: &[Real]| -> f64 {
        a.iter().zip(b).map(|(x, y)| f64::from((x - y).abs())).sum()
    };
    [
        sum(&m.map.means, &before.means),
        sum(&m.map.log_scales, &before.log_scales),
        sum(&m.map.opacity_logits, &before.opacity_logits),
        sum(&m.map.sh, &before.sh),
    ]
}

/// A learning-rate scale s makes Adam's first step (lr times the gradient's sign) s times as
/// long in every group, and scale 1 gives back exactly the configured rates.
#[test]
fn a_learning_rate_scale_scales_every_groups_step() {
    let full = step_sizes(&first_step(|_| {}));
    let quarter = step_sizes(&first_step(|m| m.set_lr_scale(0.25).unwrap()));
    for (f, q) in full.iter().zip(quarter) {
        assert!(*f > 0.0 && (q / f - 0.25).abs() < 0.01, "{q} against {f}");
    }
    let (_, a) = first_step(|_| {});
    let (_, b) = first_step(|m| {
        m.set_lr_scale(0.25).unwrap();
        m.set_lr_scale(1.0).unwrap();
    });
    assert_eq!(a.map.sh, b.map.sh);
    assert_eq!(a.map.means, b.map.means);
    let mut m = Mapper::new(MapperConfig::default()).unwrap();
    for bad in [0.0, -1.0, Real::NAN, Real::INFINITY] {
        assert!(m.set_lr_scale(bad).is_err(), "{bad}");
    }
}

/// Scales by group move each group's first step by its own scale and leave the others' steps
/// as they were.
#[test]
fn learning_rate_scales_by_group_scale_each_groups_step_alone() {
    let full = step_sizes(&first_step(|_| {}));
    let geometry = step_sizes(&first_step(|m| {
        m.set_lr_scales(Groups {
            means: 3.0,
            log_scales: 3.0,
            quats: 3.0,
            ..Groups::splat(1.0)
        })
        .unwrap()
    }));
    for (i, want) in [3.0, 3.0, 1.0, 1.0].into_iter().enumerate() {
        assert!(
            full[i] > 0.0 && (geometry[i] / full[i] - want).abs() < 0.01 * want,
            "group {i}: {} against {}",
            geometry[i],
            full[i]
        );
    }
    let mut m = Mapper::new(MapperConfig::default()).unwrap();
    let bad = Groups {
        sh: 0.0,
        ..Groups::splat(1.0)
    };
    let err = m.set_lr_scales(bad).unwrap_err();
    assert!(err.contains("sh"), "{err}");
}

/// Every Gaussian's parameters as one row of bits, the rows sorted: the map as a set.
fn rows_as_set(m: &GaussianMap) -> Vec<Vec<u64>> {
    let groups: [(&[Real], usize); 6] = [
        (&m.means, 3),
        (&m.log_scales, 3),
        (&m.quats, 4),
        (&m.opacity_logits, 1),
        (&m.sh, m.sh_coeffs * 3),
        (&m.features, m.num_features),
    ];
    let mut rows: Vec<Vec<u64>> = (0..m.len())
        .map(|i| {
            groups
                .iter()
                .flat_map(|(v, w)| v[i * w..(i + 1) * w].iter().map(|x| x.to_bits().into()))
                .chain([u64::from(m.origin[i]), u64::from(m.has_feature[i])])
                .collect()
        })
        .collect();
    rows.sort_unstable();
    rows
}

/// A refinement with `spatial_order` leaves the map it would have left without, its rows in
/// spatial order, each with its own optimiser moments (the steps after it move every Gaussian
/// as they move it in the order it was made).
#[test]
fn spatial_order_permutes_rows_with_their_moments() {
    let run = |spatial_order: bool, iterations: usize| {
        let mut cfg = MapperConfig {
            finest_level: 0,
            grow_level: 0,
            spatial_order,
            ..Default::default()
        };
        cfg.densify.interval = 10;
        cfg.densify.grad_threshold = 1e-9; // clones and splits
        cfg.prune.min_opacity = 0.79; // and pruned rows (they start at 0.8)
        let mut m = Mapper::new(cfg).unwrap();
        // Two views side by side, so that the rows come in two runs.
        let (rgb, depth, k) = wall(48, 32);
        let mut beside = Pose::identity();
        beside[(0, 3)] = 1.5;
        m.add_keyframe(rgb.clone(), depth.clone(), k, Pose::identity())
            .unwrap();
        m.add_keyframe(rgb, depth, k, beside).unwrap();
        let r = m.train(iterations).unwrap();
        (m, r)
    };
    // Refined once, after the 10th iteration; then 5 more steps (the next refinement would
    // draw split samples in row order, so that the maps part ways there).
    for iterations in [10, 15] {
        let (a, ra) = run(true, iterations);
        let (b, rb) = run(false, iterations);
        assert!(ra.cloned + ra.split > 0 && ra.pruned > 0, "{ra:?}");
        assert_eq!(
            (ra.cloned, ra.split, ra.pruned),
            (rb.cloned, rb.split, rb.pruned)
        );
        let (sa, sb) = (rows_as_set(&a.map), rows_as_set(&b.map));
        let differ = sa.iter().zip(&sb).filter(|(x, y)| x != y).count();
        assert!(
            sa.len() == sb.len() && differ == 0,
            "after {iterations}: {} against {} rows, {differ} differ",
            sa.len(),
            sb.len()
        );
        assert_ne!(a.map.means, b.map.means, "the same order");
        if iterations == 10 {
            let all = vec![true; a.map.len()];
            let order = spatial_order(&a.map.means, &all);
            assert!(
                order.iter().enumerate().all(|(i, &r)| i == r),
                "not in order"
            );
        }
    }
}
