//! A render asked for depth and alpha alone (no colour, no features: what the tracker's
//! coverage check renders) against a full render: depth and alpha the same bits, through
//! every compositing implementation the machine has, on random and hard scenes, with partial
//! tiles.

mod common;

use common::{bits, each_scene_and_path};
use legslam_core::raster::{render, RenderOptions};

#[test]
fn depth_and_alpha_alone_are_the_full_renders_bits() {
    each_scene_and_path(|seed, s, deg, simd| {
        let what = format!("scene {seed} (degree {deg}), {simd:?}");
        let opts = |all: bool| RenderOptions {
            sh_degree: deg,
            simd,
            color: all,
            features: all,
            feature_scale: 1 + seed as usize % 2,
            ..Default::default()
        };
        let full = render(&s.gaussians(), &s.camera(), &opts(true)).unwrap();
        let part = render(&s.gaussians(), &s.camera(), &opts(false)).unwrap();
        assert!(
            full.alpha.iter().any(|&a| a > 0.5) && full.color.iter().any(|&c| c != 0.0),
            "{what}: the scene must cover pixels with colour"
        );
        assert!(
            part.color.is_empty() && part.features.is_empty(),
            "{what}: no colour or features were asked for"
        );
        assert_eq!(bits(&part.alpha), bits(&full.alpha), "{what}: alpha");
        assert_eq!(bits(&part.depth), bits(&full.depth), "{what}: depth");
    });
}
