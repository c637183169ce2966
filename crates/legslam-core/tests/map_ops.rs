//! Map growth, pruning and densification on small hand-built cases.

use legslam_core::camera::{se3, Intrinsics, Pose};
use legslam_core::map::densify::{add_screen_grads, densify, DensifyConfig};
use legslam_core::map::grow::{assign_features, grow, GrowConfig, RenderedView};
use legslam_core::map::prune::{add_contributions, keep_mask, PruneConfig};
use legslam_core::map::tally::Tally;
use legslam_core::map::{FeatureGrid, GaussianMap, Keyframe, NewGaussian};
use legslam_core::rng::Rng;
use legslam_core::Real;

fn pose() -> Pose {
    let (c, s) = (0.4f64.cos(), 0.4f64.sin());
    #[rustfmt::skip]
    let p = Pose::new(
        c, 0.0, s, 1.0,
        0.0, 1.0, 0.0, -0.5,
        -s, 0.0, c, 2.0,
        0.0, 0.0, 0.0, 1.0,
    );
    p
}

/// The test keyframes' 16x12 camera.
fn camera() -> Intrinsics {
    Intrinsics {
        fx: 20.0,
        fy: 20.0,
        cx: 7.5,
        cy: 5.5,
        width: 16,
        height: 12,
    }
}

/// Grows `map` from the whole of keyframe `kf` (no render: every valid candidate is new).
fn grow_all(
    map: &mut GaussianMap,
    kf: &Keyframe,
    features: Option<&FeatureGrid>,
    origin: u32,
    cfg: &GrowConfig,
) -> usize {
    grow(map, &kf.levels[0], &kf.pose, None, features, origin, cfg)
}

/// A 16x12 keyframe looking at a wall 2 m away, with a hole of invalid depth.
fn wall() -> Keyframe {
    let k = camera();
    let rgb = (0..16 * 12 * 3).map(|i| (i % 5) as Real / 5.0).collect();
    let mut depth = vec![2.0; 16 * 12];
    depth[16 + 1] = 0.0;
    Keyframe::new(0, rgb, depth, k, pose(), 1).unwrap()
}

#[test]
fn growth_back_projects_valid_sampled_pixels() {
    let kf = wall();
    let mut map = GaussianMap::new(1, 2);
    let cfg = GrowConfig::default();
    let grid = FeatureGrid::new(vec![1.0, 2.0], 1, 1, 2).unwrap();
    let added = grow_all(&mut map, &kf, Some(&grid), 7, &cfg);
    // stride 2 from offset 1: x in 1,3,..,15 (8), y in 1,..,11 (6); pixel (1,1) is a hole.
    assert_eq!(added, 8 * 6 - 1);
    assert_eq!(map.len(), added);
    // Every centre lies on the wall: 2 m in front of the camera, at its pixel.
    let w2c = se3::inverse(&kf.pose);
    let m = &map.means[0..3];
    let pc = se3::transform_point(&w2c, &[m[0] as f64, m[1] as f64, m[2] as f64].into());
    assert!((pc[2] - 2.0).abs() < 1e-5, "{pc:?}");
    assert!(
        (20.0 * pc[0] / pc[2] + 7.5 - 3.0).abs() < 1e-4,
        "first is pixel (3, 1)"
    );
    assert_eq!(&map.features[0..2], &[1.0, 2.0]);
    assert!(map.origin.iter().all(|o| *o == 7));
    // Colour: C0 * sh + 0.5 gives back the pixel's colour.
    let c0 = legslam_core::raster::sh::basis_c0();
    let p = 16 + 3;
    assert!((c0 * map.sh[0] + 0.5 - kf.levels[0].rgb[3 * p]).abs() < 1e-5);
}

/// The colour of `plain_wall_with_a_step` at pixel (x, y): two ramps and a constant.
fn ramp(x: Real, y: Real) -> [Real; 3] {
    [0.2 + 0.01 * x, 0.5, 0.7 - 0.02 * y]
}

/// `wall()` coloured by `ramp`, with a step in depth (2 m -> 3 m) from column 10 on.
fn plain_wall_with_a_step() -> Keyframe {
    let kf = wall();
    let l = &kf.levels[0];
    let rgb = (0..16 * 12)
        .flat_map(|p| ramp((p % 16) as Real, (p / 16) as Real))
        .collect();
    let depth = (0..16 * 12)
        .map(|p| match p % 16 {
            _ if l.depth[p] == 0.0 => 0.0,
            x if x >= 10 => 3.0,
            _ => 2.0,
        })
        .collect();
    Keyframe::new(0, rgb, depth, l.intrinsics, kf.pose, 1).unwrap()
}

#[test]
fn growth_merges_smooth_blocks_of_four_candidates() {
    let merging = GrowConfig {
        merge_tolerance: 0.02,
        ..Default::default()
    };
    // Textured (colours 0.2 apart): nothing merges, the same Gaussians as without merging.
    let kf = wall();
    let (mut a, mut b) = (GaussianMap::new(1, 0), GaussianMap::new(1, 0));
    let plain = GrowConfig::default();
    let n = grow_all(&mut a, &kf, None, 0, &plain);
    assert_eq!(grow_all(&mut b, &kf, None, 0, &merging), n);
    assert_eq!(a.means, b.means);

    // Ramps of colour: candidates x in 1,3,..,15, y in 1,..,11 make 4 x 3 blocks. The block at
    // (0, 0) holds the hole (its three others stand alone), the one over candidate columns 9
    // and 11 straddles the depth step in each block row (four alone), the other eight merge.
    let kf = plain_wall_with_a_step();
    let mut map = GaussianMap::new(1, 2);
    let grid = FeatureGrid::new(vec![1.0, 2.0], 1, 1, 2).unwrap();
    let added = grow_all(&mut map, &kf, Some(&grid), 0, &merging);
    assert_eq!(added, 8 + 3 + 3 * 4);
    // log scale of a Gaussian `cells` pixels wide at depth z (f = 20)
    let width = |z: f64, cells: f64| ((z * cells / 20.0) * plain.scale as f64).ln() as Real;
    let is = |i: usize, cells: f64| {
        [2.0, 3.0]
            .iter()
            .any(|&z| (map.log_scales[3 * i] - width(z, cells)).abs() < 1e-5)
    };
    let w2c = se3::inverse(&kf.pose);
    let merged: Vec<usize> = (0..added).filter(|&i| is(i, 4.0)).collect();
    assert_eq!(merged.len(), 8);
    assert!((0..added).all(|i| merged.contains(&i) || is(i, 2.0)));
    // The first merged block is the one over columns 5-7, rows 1-3: its Gaussian sits on the
    // wall at the block's centre pixel (6, 2), in the ramps' colour there, with the feature.
    let m = &map.means[3 * merged[0]..][..3];
    let pc = se3::transform_point(&w2c, &[m[0] as f64, m[1] as f64, m[2] as f64].into());
    assert!((pc[2] - 2.0).abs() < 1e-5, "{pc:?}");
    let (u, v) = (20.0 * pc[0] / pc[2] + 7.5, 20.0 * pc[1] / pc[2] + 5.5);
    assert!((u - 6.0).abs() < 1e-4 && (v - 2.0).abs() < 1e-4, "{u} {v}");
    let c0 = legslam_core::raster::sh::basis_c0();
    let sh = &map.sh[3 * merged[0]..][..3];
    for (s, c) in sh.iter().zip(ramp(6.0, 2.0)) {
        assert!((c0 * s + 0.5 - c).abs() < 1e-5);
    }
    assert_eq!(&map.features[2 * merged[0]..][..2], &[1.0, 2.0]);
}

/// A 16x12 keyframe of a plane tilted towards the camera's right (normal `tilted_normal()` in
/// the camera's frame), a wall 4 m away from column 12 on, and a hole over pixels (1-5, 3-7)
/// but for its centre.
fn tilted_plane() -> (Keyframe, nalgebra::Vector3<f64>) {
    let k = camera();
    let n = nalgebra::Vector3::new(0.3, -0.2, -1.0).normalize();
    let depth = (0..16 * 12)
        .map(|p| {
            let (x, y) = ((p % 16) as f64, (p / 16) as f64);
            let ray = nalgebra::Vector3::new((x - k.cx) / k.fx, (y - k.cy) / k.fy, 1.0);
            match (x as usize, y as usize) {
                (1..=5, 3..=7) if (x, y) != (3.0, 5.0) => 0.0,
                (12.., _) => 4.0,
                // On the plane n . p = 2 n.z (through (0, 0, 2)).
                _ => (2.0 * n.z / n.dot(&ray)) as Real,
            }
        })
        .collect();
    let rgb = vec![0.5; 16 * 12 * 3];
    (Keyframe::new(0, rgb, depth, k, pose(), 1).unwrap(), n)
}

#[test]
fn grown_gaussians_lie_flat_along_the_depths_surface() {
    let (kf, plane) = tilted_plane();
    let flat = GrowConfig {
        flatness: 0.2,
        ..Default::default()
    };
    let mut map = GaussianMap::new(1, 0);
    let added = grow_all(&mut map, &kf, None, 0, &flat);
    assert_eq!(added, 8 * 6 - 8, "eight candidates in the hole");
    let (w2c, r) = (se3::inverse(&kf.pose), se3::rotation(&kf.pose));
    let k = camera();
    let mut seen = [0; 3];
    for i in 0..added {
        let m = &map.means[3 * i..][..3];
        let pc = se3::transform_point(&w2c, &[m[0] as f64, m[1] as f64, m[2] as f64].into());
        let x = (k.fx * pc.x / pc.z + k.cx).round() as usize;
        let y = (k.fy * pc.y / pc.z + k.cy).round() as usize;
        let q = &map.quats[4 * i..][..4];
        let rot = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            q[0] as f64,
            q[1] as f64,
            q[2] as f64,
            q[3] as f64,
        ));
        let s = &map.log_scales[3 * i..][..3];
        if (x, y) == (3, 5) {
            // Alone in the hole: no plane, so round.
            assert!(s[0] == s[1] && s[1] == s[2]);
            assert_eq!(q, [1.0, 0.0, 0.0, 0.0]);
            seen[0] += 1;
            continue;
        }
        // A disc on the surface: its thin axis (the rotation's z) along the surface's normal,
        // the tilted plane's, or the far wall's (the camera's z) beyond the step (the Gaussians
        // at columns 11 and 13 fit their plane to the pixels on their side of it, those beside
        // the hole to the pixels around it); its first axis along the slope away from the
        // camera, longer by 1 / cos of the angle the line of sight makes with the normal.
        let n = if x >= 12 {
            nalgebra::Vector3::z()
        } else {
            plane
        };
        let sight = pc.normalize();
        let axis = |c: usize| r.transpose() * (rot * nalgebra::Vector3::ith(c, 1.0));
        assert!(
            axis(2).dot(&n).abs() > 0.9999,
            "pixel ({x}, {y}): thin axis {:?}, normal {n:?}",
            axis(2)
        );
        let slope = (sight - n * n.dot(&sight)).normalize();
        assert!(axis(0).dot(&slope).abs() > 0.9999, "pixel ({x}, {y})");
        let stretch = (1.0 / n.dot(&sight).abs()).min(3.0);
        assert!(
            (s[0] - s[1] - stretch.ln() as Real).abs() < 1e-4,
            "pixel ({x}, {y})"
        );
        assert!((s[2] - s[1] - 0.2f32.ln() as Real).abs() < 1e-5);
        seen[1 + usize::from(x >= 12)] += 1;
    }
    assert_eq!(seen, [1, 6 * 6 - 9, 2 * 6]);
    // Round (the default): every Gaussian as before.
    let mut round = GaussianMap::new(1, 0);
    grow_all(&mut round, &kf, None, 0, &GrowConfig::default());
    assert!(round.quats.chunks(4).all(|q| q == [1.0, 0.0, 0.0, 0.0]));
    assert!(round
        .log_scales
        .chunks(3)
        .all(|s| s[0] == s[1] && s[1] == s[2]));
    assert_eq!(round.means, map.means);
}

#[test]
fn growth_skips_what_the_map_explains() {
    let kf = wall();
    let mut map = GaussianMap::new(1, 0);
    let n = 16 * 12;
    let (alpha, depth) = (vec![1.0; n], vec![2.0; n]);
    let view = RenderedView {
        alpha: &alpha,
        depth: &depth,
    };
    let cfg = GrowConfig::default();
    assert_eq!(
        grow(&mut map, &kf.levels[0], &kf.pose, Some(view), None, 0, &cfg),
        0
    );
    // The map's surface is 30 cm behind the wall: everything is unexplained.
    let far = vec![2.3; n];
    let view = RenderedView {
        alpha: &alpha,
        depth: &far,
    };
    assert_eq!(
        grow(&mut map, &kf.levels[0], &kf.pose, Some(view), None, 0, &cfg),
        47
    );
    // Half transparent: unexplained too.
    let half = vec![0.3; n];
    let view = RenderedView {
        alpha: &half,
        depth: &depth,
    };
    assert_eq!(
        grow(&mut map, &kf.levels[0], &kf.pose, Some(view), None, 0, &cfg),
        47
    );
}

#[test]
fn late_features_go_to_the_keyframes_gaussians_only() {
    let kf = wall();
    let mut map = GaussianMap::new(1, 3);
    let cfg = GrowConfig::default();
    grow_all(&mut map, &kf, None, 1, &cfg);
    let n1 = map.len();
    grow_all(&mut map, &kf, None, 2, &cfg);
    assert!(map.features.iter().all(|v| *v == 0.0) && !map.has_feature.iter().any(|h| *h));
    // Left half of the grid is (1,0,0), right half (0,1,0).
    let grid = FeatureGrid::new(vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0], 2, 1, 3).unwrap();
    assert_feature_side(&map, &kf, &grid, n1);
}

fn assert_feature_side(map: &GaussianMap, kf: &Keyframe, grid: &FeatureGrid, n1: usize) {
    let mut map = map.clone();
    assign_features(&mut map, &kf.levels[0], &kf.pose, 1, grid);
    assert!(map.has_feature[..n1].iter().all(|h| *h));
    assert!(!map.has_feature[n1..].iter().any(|h| *h));
    // The first Gaussian is at pixel x = 3 of 16 (left): mostly the left feature.
    assert!(map.features[0] > 0.9 && map.features[1] < 0.1);
    // The last of keyframe 1 is at x = 15 (right).
    let last = n1 - 1;
    assert!(map.features[3 * last + 1] > 0.9);
}

fn one(map: &mut GaussianMap, log_scale: Real, logit: Real) {
    map.push(NewGaussian {
        mean: [0.0, 0.0, 1.0],
        log_scale: [log_scale, log_scale - 1.0, log_scale],
        quat: [1.0, 0.0, 0.0, 0.0],
        opacity_logit: logit,
        sh: &[0.1, 0.2, 0.3],
        feature: &[],
        origin: 0,
    });
}

#[test]
fn pruning_removes_transparent_and_huge_gaussians() {
    let mut map = GaussianMap::new(1, 0);
    one(&mut map, -3.0, 0.0); // kept
    one(&mut map, -3.0, -5.0); // opacity 0.0067 < 0.02
    one(&mut map, 0.0, 0.0); // 1 m > 0.1 x extent 2 m
    let keep = keep_mask(&map, 2.0, None, None, &PruneConfig::default());
    assert_eq!(keep, vec![true, false, false]);
    let screen = PruneConfig {
        max_screen_radius: 10.0,
        ..Default::default()
    };
    let keep = keep_mask(&map, 100.0, Some(&[5.0, 5.0, 50.0]), None, &screen);
    assert_eq!(keep, vec![true, false, false]);
}

#[test]
fn pruning_by_contribution_needs_enough_views_and_spares_rows_not_tallied() {
    let mut map = GaussianMap::new(1, 0);
    for _ in 0..4 {
        one(&mut map, -3.0, 0.0);
    }
    // Three views whose render pixels each weigh 4 in the tally's unit: Gaussian 0 makes 0.1
    // in each, Gaussian 1 as little but is off screen in one view, Gaussian 2 makes 1 in each;
    // Gaussian 3 came after the tally started.
    let mut seen = Tally::default();
    for view in 0..3 {
        let radius_1 = if view == 0 { 0.0 } else { 2.0 };
        add_contributions(
            &mut seen,
            &[0.025, 0.025, 0.25],
            &[2.0, radius_1, 2.0],
            &[0, 1, 2],
            4.0,
        );
    }
    assert_eq!(seen.count, vec![3, 2, 3]);
    assert_eq!(seen.count(3), 0);
    assert!((seen.mean(0).unwrap() - 0.1).abs() < 1e-6 && seen.mean(3).is_none());
    let cfg = PruneConfig {
        min_contribution: 0.5,
        contribution_views: 3,
        ..Default::default()
    };
    let keep = keep_mask(&map, 2.0, None, Some(&seen), &cfg);
    assert_eq!(keep, vec![false, true, true, true]);
    let off = PruneConfig::default(); // min_contribution 0: nothing pruned by contribution
    assert_eq!(keep_mask(&map, 2.0, None, Some(&seen), &off), vec![true; 4]);
}

#[test]
fn densification_clones_small_and_splits_large() {
    let mut map = GaussianMap::new(1, 0);
    one(&mut map, -6.0, 1.0); // small: cloned
    one(&mut map, -2.0, 1.0); // large (0.135 > 0.01 x 2): split
    one(&mut map, -6.0, 1.0); // small gradient: untouched
    let stats = Tally {
        sum: vec![1.0, 1.0, 1e-6],
        count: vec![2, 2, 2],
    };
    let mut rng = Rng::new(0);
    let d = densify(&mut map, &stats, 2.0, &DensifyConfig::default(), &mut rng);
    assert_eq!((d.cloned, d.split), (1, 1));
    assert_eq!(d.sources, vec![0, 1, 1]);
    assert_eq!(map.len(), 6);
    map.retain(&d.keep);
    assert_eq!(map.len(), 5);
    // The split children are the last two rows: 1.6x smaller, centres moved apart.
    let ls = &map.log_scales;
    assert!((ls[3 * 3] - (-2.0 - (1.6 as Real).ln())).abs() < 1e-5);
    assert_ne!(map.means[3 * 3], map.means[3 * 4]);
    // Cloned row is an exact copy.
    assert_eq!(&map.means[0..3], &map.means[3 * 2..3 * 3]);
}

#[test]
fn densification_respects_the_cap() {
    let mut map = GaussianMap::new(1, 0);
    for _ in 0..4 {
        one(&mut map, -6.0, 1.0);
    }
    let stats = Tally {
        sum: vec![1.0; 4],
        count: vec![1; 4],
    };
    let cfg = DensifyConfig {
        max_gaussians: 6,
        ..Default::default()
    };
    densify(&mut map, &stats, 2.0, &cfg, &mut Rng::new(1));
    assert_eq!(map.len(), 6);
}

#[test]
fn gradient_statistics_are_in_normalised_device_coordinates() {
    // Two visible Gaussians and one culled; pixel gradients of a 320 x 240 render.
    let mut stats = Tally::default();
    add_screen_grads(
        &mut stats,
        &[1e-3, 0.0, 0.0, 2e-3, 5.0, 5.0],
        &[0, 1],
        320,
        240,
    );
    add_screen_grads(&mut stats, &[3e-3, 0.0, 0.0, 0.0, 5.0, 5.0], &[0], 320, 240);
    assert_eq!(stats.count, vec![2, 1, 0]);
    // x scales by width / 2, y by height / 2: (0.16 + 0.48) and 0.24.
    assert!((stats.sum[0] - 0.64).abs() < 1e-6, "{:?}", stats.sum);
    assert!((stats.sum[1] - 0.24).abs() < 1e-6, "{:?}", stats.sum);
    assert_eq!(stats.sum[2], 0.0);
}
