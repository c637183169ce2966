//! Rasterizer benchmark on a realistic scene: one Gaussian per valid pixel of a real 640x480
//! 7-Scenes depth frame (from `../shared/data`, beside the checkout), rendered from a view
//! 5 cm and 2 degrees off the frame's own, at 640x480, for K = 0 and 64 on 1 and 2 threads;
//! K = 64 both at every pixel and 4 times coarser (160x120, `feature_scale` 4: about the
//! feature target's own resolution). The coarse layer renders as the mapper trains it: each
//! pixel the main layer's image at one point of its block (`feature_origin`), here the block's
//! centre; LEGSLAM_BENCH_FEATURE_BLOCKS=1 renders each pixel's block instead (the mapper option
//! `feature_jitter` false, and this bench's case before 2026-12-07).
//! Without the data folder a synthetic wall of the same size stands in. Each case runs the
//! portable compositing and the AVX2 one (where the CPU has it) alternately; the ratio is the
//! speed-up over the portable path.
//!
//! cargo bench -p legslam-core --bench raster   (LEGSLAM_BENCH_SAMPLES, default 10)

#[path = "common/mod.rs"]
mod common;

use std::path::PathBuf;
use std::sync::LazyLock;

use common::{compare, env, samples, variant};
use legslam_core::camera::{Intrinsics, Pose};
use legslam_core::raster::{
    backward_into, render, render_into, vector_paths, BackwardScratch, Camera, Gaussians,
    Gradients, ImageGrads, RenderOptions, Rendered, Simd,
};
use legslam_core::Real;

const W: usize = 640;
const H: usize = 480;
const F: f64 = 585.0;

struct Scene {
    means: Vec<Real>,
    log_scales: Vec<Real>,
    quats: Vec<Real>,
    opacity_logits: Vec<Real>,
    sh: Vec<Real>,
    features: Vec<Real>,
}

fn depth_frame() -> (Vec<f32>, &'static str) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data/7scenes_tsdf_fusion/data/frame-000000.depth.png");
    let Ok(file) = std::fs::File::open(&path) else {
        // A slanted wall 1.5-3 m away.
        let d = (0..W * H)
            .map(|p| 1.5 + 1.5 * (p % W) as f32 / W as f32)
            .collect();
        return (d, "synthetic wall (../shared/data absent)");
    };
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .expect("7-Scenes depth PNG");
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    reader.next_frame(&mut buf).unwrap();
    let d = buf
        .chunks_exact(2)
        .map(|b| match u16::from_be_bytes([b[0], b[1]]) {
            0 | 65535 => 0.0,
            v => v as f32 / 1000.0,
        })
        .collect();
    (d, "7-Scenes frame 0 depth")
}

static SCENE: LazyLock<Scene> = LazyLock::new(|| {
    let (depth, source) = depth_frame();
    let mut s = Scene {
        means: vec![],
        log_scales: vec![],
        quats: vec![],
        opacity_logits: vec![],
        sh: vec![],
        features: vec![],
    };
    let mut n = 0u64;
    for (p, &z) in depth.iter().enumerate() {
        if z <= 0.0 {
            continue;
        }
        let (u, v) = ((p % W) as f64, (p / W) as f64);
        let z = z as f64;
        s.means.extend([
            ((u - 319.5) * z / F) as Real,
            ((v - 239.5) * z / F) as Real,
            z as Real,
        ]);
        // The pixel footprint at that depth.
        let ls = (z / F).ln() as Real;
        s.log_scales.extend([ls, ls, ls]);
        s.quats.extend([1.0, 0.0, 0.0, 0.0]);
        s.opacity_logits.push(2.0);
        n += 1;
        let c = (n % 97) as Real / 97.0 - 0.5;
        s.sh.extend([c, -c, 0.5 * c]);
        s.features
            .extend((0..64).map(|k| ((n * 31 + k) % 101) as Real / 101.0 - 0.5));
    }
    eprintln!("scene: {} Gaussians from {source}", s.opacity_logits.len());
    s
});

fn gaussians(k: usize) -> Gaussians<'static> {
    let s = &*SCENE;
    Gaussians {
        means: &s.means,
        log_scales: &s.log_scales,
        quats: &s.quats,
        opacity_logits: &s.opacity_logits,
        sh: &s.sh,
        sh_coeffs: 1,
        features: if k == 0 { &[] } else { &s.features },
        num_features: k,
    }
}

fn camera() -> Camera {
    let intr = Intrinsics {
        fx: F,
        fy: F,
        cx: 319.5,
        cy: 239.5,
        width: W,
        height: H,
    };
    let (c, s) = (2f64.to_radians().cos(), 2f64.to_radians().sin());
    #[rustfmt::skip]
    let w2c = Pose::new(
        c, 0.0, s, 0.05,
        0.0, 1.0, 0.0, 0.0,
        -s, 0.0, c, 0.0,
        0.0, 0.0, 0.0, 1.0,
    );
    Camera::new(intr, &w2c).unwrap()
}

fn options(simd: Simd, feature_scale: usize, for_backward: bool) -> RenderOptions {
    let centre = (feature_scale as Real - 1.0) / 2.0;
    let points = feature_scale > 1 && env("LEGSLAM_BENCH_FEATURE_BLOCKS", 0) == 0;
    RenderOptions {
        simd,
        feature_scale,
        for_backward,
        feature_origin: points.then_some([centre; 2]),
        ..Default::default()
    }
}

/// Forward, or forward and backward, of the scene with `k` features through `simd`, with the
/// buffers a training loop keeps.
fn pass(k: usize, scale: usize, simd: Simd, backward: bool) -> impl FnMut() {
    let (g, cam, opts) = (gaussians(k), camera(), options(simd, scale, backward));
    let d_color = vec![0.1; W * H * 3];
    let d_depth = vec![0.1; W * H];
    let d_feat = vec![0.01; (W / scale) * (H / scale) * k];
    let mut r = Rendered::default();
    let mut scratch = BackwardScratch::default();
    let mut grads = Gradients::default();
    move || {
        render_into(&g, &cam, &opts, &mut r).unwrap();
        if backward {
            let image_grads = ImageGrads {
                color: Some(&d_color),
                depth: Some(&d_depth),
                alpha: None,
                features: (k > 0).then_some(&d_feat[..]),
            };
            backward_into(&g, &cam, &r, &image_grads, &mut scratch, &mut grads).unwrap();
        }
    }
}

fn main() {
    let r = render(&gaussians(0), &camera(), &RenderOptions::default()).unwrap();
    eprintln!(
        "640x480: {} tile-Gaussian pairs, {} of {} Gaussians on screen",
        r.num_pairs(),
        r.radii.iter().filter(|v| **v > 0.0).count(),
        r.radii.len()
    );
    let n = samples(10);
    let simds: Vec<Simd> = [Simd::Portable].into_iter().chain(vector_paths()).collect();
    if simds.len() == 1 {
        eprintln!("no AVX2 or NEON on this CPU: the portable path only");
    }
    for backward in [false, true] {
        for (k, scale) in [(0, 1), (64, 1), (64, 4)] {
            for threads in [1, 2] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let what = if backward {
                    "forward+backward"
                } else {
                    "forward"
                };
                let at = if scale > 1 {
                    format!("/{scale}")
                } else {
                    String::new()
                };
                let case = format!("{what} K{k}{at} t{threads}");
                if !common::selected(&case) {
                    continue;
                }
                let mut variants: Vec<_> = simds
                    .iter()
                    .map(|&simd| {
                        let mut run = pass(k, scale, simd, backward);
                        let pool = &pool;
                        variant(simd.name(), move || pool.install(&mut run))
                    })
                    .collect();
                compare(&case, n, &mut variants);
            }
        }
    }
}
