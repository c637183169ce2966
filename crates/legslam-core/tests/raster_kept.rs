//! The backward pass reading the falloffs a training render kept (`for_backward`) against the
//! backward pass evaluating them again: every gradient the same bits, through each compositing
//! implementation the machine has, on random and hard scenes, with features in the main layer
//! and in a coarser one, and with partial tiles.

mod common;

use common::{assert_same_gradients, hard_scene, random_scene, render_and_backward};
use legslam_core::raster::{vector_paths, RenderOptions, Simd};

#[test]
fn kept_falloffs_give_the_gradients_of_evaluated_ones() {
    let simds: Vec<Simd> = [Simd::Portable].into_iter().chain(vector_paths()).collect();
    for seed in 0..4u64 {
        let (w, h) = [(64, 48), (37, 29), (100, 17), (16, 16)][seed as usize];
        let k = [0, 5, 8, 19][seed as usize];
        for (i, (s, deg)) in [
            (random_scene(seed, 400, w, h, 3, k), 3),
            (hard_scene(seed + 10, w, h, 1, k), 1),
        ]
        .iter()
        .enumerate()
        {
            for &simd in &simds {
                for scale in [1, 2] {
                    let opts = |for_backward| RenderOptions {
                        sh_degree: *deg,
                        simd,
                        feature_scale: scale,
                        for_backward,
                        ..Default::default()
                    };
                    let what = format!("scene {seed}/{i}, {simd:?}, feature scale {scale}");
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
            }
        }
    }
}
