//! The backward pass reading the falloffs a training render kept (`for_backward`) against the
//! backward pass evaluating them again: every gradient the same bits, through each compositing
//! implementation the machine has, on random and hard scenes, with features in the main layer
//! and in a coarser one, and with partial tiles.

mod common;

use common::{assert_same_gradients, each_scene_and_path, render_and_backward};
use legslam_core::raster::RenderOptions;

#[test]
fn kept_falloffs_give_the_gradients_of_evaluated_ones() {
    each_scene_and_path(|seed, s, deg, simd| {
        for scale in [1, 2] {
            let opts = |for_backward| RenderOptions {
                sh_degree: deg,
                simd,
                feature_scale: scale,
                for_backward,
                ..Default::default()
            };
            let what = format!("scene {seed} (degree {deg}), {simd:?}, feature scale {scale}");
            let (rk, gk) = render_and_backward(s, &opts(true), seed);
            let (re, ge) = render_and_backward(s, &opts(false), seed);
            assert_eq!(
                (&rk.color, &rk.features),
                (&re.color, &re.features),
                "{what}: the images"
            );
            assert_eq!(gk.rows, ge.rows, "{what}: rows on screen");
            assert_same_gradients(&gk, &ge, &what);
            assert!(
                gk.opacity_logits.iter().any(|v| *v != 0.0),
                "{what}: no gradient reached opacity"
            );
        }
    });
}
