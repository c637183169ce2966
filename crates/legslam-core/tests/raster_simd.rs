//! Each of the CPU's vector rasterizers (AVX2 and AVX-512 on x86-64, NEON on aarch64) against
//! the portable one:
//! every rendered image and every gradient the same bits, on random and hard scenes, with and
//! without features, at every SH degree and with odd image sizes (partial tiles). Runs where
//! the CPU has one of them; the portable path itself is checked against the f64 reference
//! (raster_reference.rs) and by finite differences (raster_grad.rs, in f64 builds).
#![cfg(not(feature = "f64"))]

mod common;

use common::{
    assert_same_gradients, assert_same_images, hard_scene, random_scene, render_and_backward, Scene,
};
use legslam_core::raster::{
    avx2_available, avx512_available, neon_available, render, vector_paths, Gradients,
    RenderOptions, Rendered, Simd,
};

fn run(s: &Scene, sh_degree: usize, scale: usize, simd: Simd, seed: u64) -> (Rendered, Gradients) {
    let opts = RenderOptions {
        sh_degree,
        simd,
        feature_scale: scale,
        for_backward: seed % 2 == 0,
        ..Default::default()
    };
    render_and_backward(s, &opts, seed)
}

#[test]
fn every_vector_path_renders_and_differentiates_the_portable_bits() {
    let paths = vector_paths();
    if paths.is_empty() {
        eprintln!("no AVX2 or NEON on this CPU: only the portable path runs here");
        return;
    }
    let mut scenes = Vec::new();
    for seed in 0..4 {
        let (w, h) = [(64, 48), (37, 29), (100, 17), (16, 16)][seed as usize];
        let k = [0, 5, 8, 19][seed as usize];
        scenes.push((random_scene(seed, 500, w, h, 3, k), 3, 1));
        scenes.push((hard_scene(seed + 10, w, h, 1, k), 1, 1 + seed as usize % 2));
    }
    for (i, (s, deg, scale)) in scenes.iter().enumerate() {
        let (rp, gp) = run(s, *deg, *scale, Simd::Portable, i as u64);
        assert!(
            rp.alpha.iter().any(|&a| a > 0.5),
            "scene {i} covers no pixel"
        );
        assert!(
            gp.means.iter().any(|v| *v != 0.0),
            "scene {i} has no gradient"
        );
        for &simd in &paths {
            let (ra, ga) = run(s, *deg, *scale, simd, i as u64);
            assert_same_images(&ra, &rp, &format!("scene {i}, {simd:?}"));
            assert_same_gradients(&ga, &gp, &format!("scene {i}, {simd:?}"));
        }
    }
}

#[test]
fn asking_for_a_vector_path_the_cpu_lacks_is_an_error() {
    let s = random_scene(1, 10, 16, 16, 0, 0);
    for (simd, here) in [
        (Simd::Avx2, avx2_available()),
        (Simd::Avx512, avx512_available()),
        (Simd::Neon, neon_available()),
    ] {
        let opts = RenderOptions {
            simd,
            ..Default::default()
        };
        let r = render(&s.gaussians(), &s.camera(), &opts);
        assert_eq!(r.is_ok(), here, "{simd:?}");
    }
}
