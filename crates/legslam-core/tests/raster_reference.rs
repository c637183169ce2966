//! The tiled, parallel forward pass against the plain per-pixel f64 reference.

mod common;

use common::{hard_scene, random_scene, random_scene_in_view, reference_render, Scene};
use legslam_core::camera::Intrinsics;
use legslam_core::raster::{backward, render, ImageGrads, RasterConfig, RenderOptions};
use legslam_core::Real;

/// Largest absolute difference, and the fraction of values off by more than `tol`.
fn compare(fast: &[Real], reference: &[f64], tol: f64) -> (f64, f64) {
    assert_eq!(fast.len(), reference.len());
    let mut worst: f64 = 0.0;
    let mut off = 0;
    for (a, b) in fast.iter().zip(reference) {
        let d = (*a as f64 - b).abs();
        worst = worst.max(d);
        if d > tol {
            off += 1;
        }
    }
    (worst, off as f64 / fast.len().max(1) as f64)
}

/// Each image of the fast pass agrees with the reference's: f64 builds to rounding; f32 builds
/// may flip a cut-off decision (alpha at exactly 1/255, or the stop) on a rare pixel, which
/// moves it by at most a few percent.
fn assert_agree(what: &str, images: &[(&str, &Vec<Real>, &Vec<f64>)]) {
    let (tol, max_flipped) = if cfg!(feature = "f64") {
        (1e-9, 0.0)
    } else {
        (2e-4, 0.003)
    };
    for &(name, a, b) in images {
        let (worst, flipped) = compare(a, b, tol);
        assert!(
            flipped <= max_flipped,
            "{what}{name}: {:.3}% of values differ by more than {tol} (worst {worst})",
            100.0 * flipped
        );
        assert!(worst < 0.05, "{what}{name}: worst difference {worst}");
    }
}

fn check(scene: &Scene, sh_degree: usize, cfg: RasterConfig) {
    let opts = RenderOptions {
        sh_degree,
        config: cfg,
        ..Default::default()
    };
    let fast = render(&scene.gaussians(), &scene.camera(), &opts).unwrap();
    let reference = reference_render(scene, sh_degree, &cfg);
    assert_agree(
        "",
        &[
            ("color", &fast.color, &reference.color),
            ("depth", &fast.depth, &reference.depth),
            ("alpha", &fast.alpha, &reference.alpha),
            ("features", &fast.features, &reference.features),
        ],
    );
    // What the backward walk sums of each Gaussian's blending weights.
    let g = scene.gaussians();
    let walked = backward(&g, &scene.camera(), &fast, &ImageGrads::default()).unwrap();
    let tol = |b: f64| if cfg!(feature = "f64") { 1e-9 } else { 1e-3 } * (1.0 + b);
    let off = (walked.contribution.iter().zip(&reference.weights))
        .filter(|(a, b)| (**a as f64 - **b).abs() > tol(**b))
        .count();
    assert!(
        off as f64 <= 0.005 * g.len() as f64,
        "contribution: {off} of {} Gaussians differ from the reference's weights",
        g.len()
    );
    for (i, (a, b)) in walked
        .contribution
        .iter()
        .zip(&reference.weights)
        .enumerate()
    {
        assert!(
            (*a as f64 - b).abs() <= 0.05 * (1.0 + b),
            "contribution of Gaussian {i}: {a} against the reference's {b}"
        );
    }
    assert!(
        fast.alpha.iter().any(|&a| a > 0.5),
        "the scene should cover pixels"
    );
}

#[test]
fn matches_reference_on_random_scenes() {
    for seed in 0..6 {
        let degree = seed as usize % 4;
        let scene = random_scene(seed, 60, 67, 45, degree, 5);
        check(&scene, degree, RasterConfig::default());
    }
}

#[test]
fn matches_reference_on_hard_scenes() {
    for seed in 0..4 {
        let scene = hard_scene(seed, 50, 37, 1, 3);
        check(&scene, 1, RasterConfig::default());
    }
}

#[test]
fn matches_reference_without_early_stop() {
    let cfg = RasterConfig {
        transmittance_min: 0.0,
        ..Default::default()
    };
    let scene = random_scene(42, 200, 40, 40, 0, 2);
    check(&scene, 0, cfg);
}

#[test]
fn renders_many_feature_channels_and_lower_degree_than_stored() {
    let scene = random_scene(7, 30, 33, 20, 3, 130);
    check(&scene, 3, RasterConfig::default());
    // colour from only the first SH band of degree-3 coefficients
    check(&scene, 0, RasterConfig::default());
}

#[test]
fn bad_cut_offs_are_refused() {
    let scene = random_scene(5, 10, 16, 16, 0, 2);
    for bad in [1.0, -0.1, Real::NAN] {
        let opts = RenderOptions {
            config: RasterConfig {
                feature_transmittance_min: bad,
                ..Default::default()
            },
            ..Default::default()
        };
        let err = render(&scene.gaussians(), &scene.camera(), &opts).unwrap_err();
        assert!(err.contains("feature_transmittance_min"), "{err}");
    }
}

#[test]
fn empty_and_fully_culled_scenes_render_black() {
    let mut scene = random_scene(3, 0, 20, 10, 0, 2);
    let opts = RenderOptions::default();
    let out = render(&scene.gaussians(), &scene.camera(), &opts).unwrap();
    assert!(out.color.iter().all(|v| *v == 0.0) && out.alpha.iter().all(|v| *v == 0.0));
    // one Gaussian behind the camera
    let mut rng = common::Rng::new(1);
    scene.push(&mut rng, [0.0, 0.0, -1.0], [-1.0; 3], 3.0);
    let out = render(&scene.gaussians(), &scene.camera(), &opts).unwrap();
    assert_eq!(out.num_pairs(), 0);
    assert_eq!(out.radii, vec![0.0]);
}

#[test]
fn render_is_deterministic() {
    let scene = random_scene(11, 300, 64, 48, 1, 4);
    let opts = RenderOptions {
        sh_degree: 1,
        ..Default::default()
    };
    let a = render(&scene.gaussians(), &scene.camera(), &opts).unwrap();
    let b = render(&scene.gaussians(), &scene.camera(), &opts).unwrap();
    assert_eq!(a.color, b.color);
    assert_eq!(a.features, b.features);
}

/// Features point-sampled at a coarser scale (`feature_origin` o) are the main layer's image at
/// the points (s i + o[0], s j + o[1]): the plain reference of a camera whose pixels lie there
/// (focal lengths divided by s, principal point moved to o and divided by s, the dilation by
/// s^2, so that each footprint is the main layer's), stopping a pixel at the features' own
/// cut-off. They differ from the render of each block.
#[test]
fn features_point_sampled_at_a_coarser_scale_match_the_points_reference() {
    for (seed, scale, origin) in [
        (31u64, 2usize, [0.0, 1.0]),
        (32, 4, [1.75, -0.5]),
        (33, 3, [2.4, 0.3]),
    ] {
        let scene = random_scene_in_view(seed, 300, 72, 48, 1, 6);
        let cfg = RasterConfig::default();
        let opts = RenderOptions {
            sh_degree: 1,
            feature_scale: scale,
            feature_origin: Some(origin),
            config: cfg,
            ..Default::default()
        };
        let fast = render(&scene.gaussians(), &scene.camera(), &opts).unwrap();
        let s = scale as f64;
        let k = scene.intr;
        let mut points = scene.clone();
        points.intr = Intrinsics {
            fx: k.fx / s,
            fy: k.fy / s,
            cx: (k.cx - origin[0] as f64) / s,
            cy: (k.cy - origin[1] as f64) / s,
            width: k.width / scale,
            height: k.height / scale,
        };
        let points_cfg = RasterConfig {
            transmittance_min: cfg.feature_transmittance_min,
            dilation: cfg.dilation / (s * s) as Real,
            ..cfg
        };
        let reference = reference_render(&points, 1, &points_cfg);
        assert_eq!(
            (fast.feature_width, fast.feature_height),
            (points.intr.width, points.intr.height)
        );
        assert_agree(
            &format!("scale {scale} "),
            &[("features", &fast.features, &reference.features)],
        );
        assert!(fast.features.iter().any(|v| v.abs() > 0.1));
        let blocks = render(
            &scene.gaussians(),
            &scene.camera(),
            &RenderOptions {
                feature_origin: None,
                ..opts
            },
        )
        .unwrap();
        let apart = (fast.features.iter().zip(&blocks.features))
            .filter(|(a, b)| (*a - *b).abs() > 1e-2)
            .count();
        assert!(
            apart > fast.features.len() / 10,
            "scale {scale}: {apart} apart"
        );
    }
}

/// A feature scale of zero, or a sample point that is not a number, is refused by name.
#[test]
fn a_zero_feature_scale_or_a_non_finite_origin_is_refused() {
    let scene = random_scene(5, 10, 32, 24, 1, 3);
    for (scale, origin, name) in [
        (0, None, "feature_scale"),
        (2, Some([Real::NAN, 0.0]), "feature_origin"),
        (2, Some([0.0, Real::INFINITY]), "feature_origin"),
    ] {
        let opts = RenderOptions {
            feature_scale: scale,
            feature_origin: origin,
            ..Default::default()
        };
        let err = render(&scene.gaussians(), &scene.camera(), &opts).unwrap_err();
        assert!(err.contains(name), "{err}");
    }
}

/// Features asked for at a coarser scale come from the same projection but match the plain
/// reference of an image that many times smaller (intrinsics scaled about pixel centres), which
/// stops a pixel at the features' own transmittance cut-off; the other images stay the
/// full-size reference's. (Sizes divide by the scale: otherwise the smaller image's field of
/// view, which clamps the projection's Jacobian, is a fraction of a pixel narrower than the
/// main one's, which the coarse layer follows.)
#[test]
fn features_at_a_coarser_scale_match_the_smaller_images_reference() {
    let cut_offs = [RasterConfig::default().feature_transmittance_min, 0.05, 0.2];
    for ((seed, scale), feature_t_min) in [(21u64, 2usize), (22, 3), (23, 4)]
        .into_iter()
        .zip(cut_offs)
    {
        let scene = random_scene(seed, 300, 72, 48, 1, 6);
        let cfg = RasterConfig {
            feature_transmittance_min: feature_t_min,
            ..Default::default()
        };
        let opts = RenderOptions {
            sh_degree: 1,
            feature_scale: scale,
            config: cfg,
            ..Default::default()
        };
        let fast = render(&scene.gaussians(), &scene.camera(), &opts).unwrap();
        let full = reference_render(&scene, 1, &cfg);
        let mut small = scene.clone();
        small.intr = scene.intr.scaled(1.0 / scale as f64);
        let features_cfg = RasterConfig {
            transmittance_min: feature_t_min,
            ..cfg
        };
        let coarse = reference_render(&small, 1, &features_cfg);
        // The cut-off tells: the colour's would render other features.
        let other = reference_render(&small, 1, &cfg);
        if feature_t_min >= 0.01 {
            let moved = (coarse.features.iter().zip(&other.features))
                .filter(|(a, b)| (*a - *b).abs() > 1e-3)
                .count();
            assert!(moved > 0, "scale {scale}: no pixel reaches either cut-off");
        }
        assert_eq!(
            (fast.feature_width, fast.feature_height),
            (small.intr.width, small.intr.height)
        );
        assert_agree(
            &format!("scale {scale} "),
            &[
                ("color", &fast.color, &full.color),
                ("alpha", &fast.alpha, &full.alpha),
                ("features", &fast.features, &coarse.features),
            ],
        );
        assert!(fast.features.iter().any(|v| v.abs() > 0.1));
    }
}
