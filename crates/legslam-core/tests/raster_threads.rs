//! The rasterizer gives the same bits on any number of threads: every image and every gradient,
//! the pose's included (summed per fixed chunk of Gaussians, in order), on a scene of several
//! chunks, with the features on a coarser layer, on the portable path and on the CPU's vector
//! paths where it has them.

mod common;

use common::{assert_same_gradients, assert_same_images, random_scene, render_and_backward};
use legslam_core::raster::{vector_paths, RenderOptions, Simd};

#[test]
fn any_thread_count_gives_the_same_bits() {
    // 6000 Gaussians: six of the projection's and the backward's chunks of 1024.
    let s = random_scene(3, 6000, 96, 72, 3, 8);
    for simd in [Simd::Portable].into_iter().chain(vector_paths()) {
        let opts = RenderOptions {
            sh_degree: 3,
            simd,
            feature_scale: 2,
            for_backward: true,
            ..Default::default()
        };
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| render_and_backward(&s, &opts, 5))
        };
        let (r1, g1) = on(1);
        assert!(
            g1.pose.iter().any(|v| *v != 0.0),
            "{simd:?}: the scene gives no pose gradient"
        );
        for threads in [2, 3] {
            let (r, g) = on(threads);
            let what = format!("{simd:?}, {threads} threads");
            assert_same_images(&r, &r1, &what);
            assert_same_gradients(&g, &g1, &what);
        }
    }
}
