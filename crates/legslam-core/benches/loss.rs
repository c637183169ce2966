//! Loss benchmarks: SSIM value and gradient at 640x480x3 and 320x240x3 (on a CPU with AVX2 also
//! with the baseline loops, "/base"), and the mapper's full combined loss (colour L1 + SSIM,
//! depth, K = 64 features) at 320x240, on 1 and 2 threads.
//!
//! cargo bench -p legslam-core --bench loss

use legslam_core::loss::{
    DepthInputs, FeatureInputs, FeatureTarget, Loss, LossGrads, LossInputs, Ssim,
};
use legslam_core::Real;

/// Deterministic pseudo-random values in [0, 1).
fn noise(n: usize, seed: u64) -> Vec<Real> {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as Real / (1u64 << 24) as Real
        })
        .collect()
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
}

/// "<width>x<height>/t<threads>[/base]"
const SSIM_CASES: [&str; 8] = [
    "640x480/t1",
    "640x480/t1/base",
    "640x480/t2",
    "640x480/t2/base",
    "320x240/t1",
    "320x240/t1/base",
    "320x240/t2",
    "320x240/t2/base",
];

fn main() {
    divan::main();
}

#[divan::bench(args = SSIM_CASES, sample_count = 20, sample_size = 1)]
fn ssim_value_and_grad(bencher: divan::Bencher, case: &str) {
    let mut parts = case.split('/');
    let (size, t) = (parts.next().unwrap(), parts.next().unwrap());
    let base = parts.next() == Some("base");
    let (w, h) = size.split_once('x').unwrap();
    let (w, h): (usize, usize) = (w.parse().unwrap(), h.parse().unwrap());
    let pool = pool(t[1..].parse().unwrap());
    let (x, y) = (noise(w * h * 3, 1), noise(w * h * 3, 2));
    let mut grad = vec![0.0; x.len()];
    let mut ssim = Ssim::with_avx2(!base);
    bencher
        .bench_local(|| pool.install(|| ssim.value_and_grad(&x, &y, w, h, 3, &mut grad).unwrap()));
}

#[divan::bench(args = [1, 2], sample_count = 20, sample_size = 1)]
fn full_loss_320x240_k64(bencher: divan::Bencher, threads: usize) {
    let (w, h, k) = (320, 240, 64);
    let n = w * h;
    let pool = pool(threads);
    let (color, target_color) = (noise(n * 3, 3), noise(n * 3, 4));
    let (depth, target_depth) = (noise(n, 5), noise(n, 6));
    let (feat, target_feat) = (noise(n * k, 7), noise(n * k, 8));
    let (mut gc, mut gd, mut gf) = (vec![0.0; n * 3], vec![0.0; n], vec![0.0; n * k]);
    let mut loss = Loss::default();
    bencher.bench_local(|| {
        let inputs = LossInputs {
            width: w,
            height: h,
            color: &color,
            target_color: &target_color,
            color_mask: None,
            depth: Some(DepthInputs {
                rendered: &depth,
                target: &target_depth,
            }),
            features: Some(FeatureInputs {
                rendered: &feat,
                target: FeatureTarget::Pixels(&target_feat),
                channels: k,
                mask: None,
            }),
        };
        let grads = LossGrads {
            color: &mut gc,
            depth: Some(&mut gd),
            features: Some(&mut gf),
        };
        pool.install(|| loss.evaluate(&inputs, grads).unwrap())
    });
}
