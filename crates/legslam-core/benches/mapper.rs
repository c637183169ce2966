//! Mapper-iteration benchmark on a realistic map: every 12th frame of the 1000-frame 7-Scenes
//! sequence in `../shared/data` (beside the checkout) becomes a keyframe at its ground-truth
//! pose, with `SETUP_ITERS` mapping iterations after each (growth, densification and pruning
//! as in a SLAM run), the SLAM's mapper options at 640x480 (training at 320x240, SH degree 3,
//! K = 64 features on a smooth synthetic patch grid), then trained on until every keyframe
//! trains at 320x240. Then single iterations (render + loss + backward + step) are timed, per
//! phase, on 2 threads, with the portable compositing and each vector one the CPU has (AVX2,
//! AVX-512 or NEON) in turn, and on a second map grown the same way with pruning by
//! contribution.
//!
//! cargo bench -p legslam-core --bench mapper
//! Environment: LEGSLAM_BENCH_K (feature channels, default 64), LEGSLAM_BENCH_SETUP_ITERS
//! (default 10), LEGSLAM_BENCH_ITERS (timed iterations per round, default 20),
//! LEGSLAM_BENCH_PRUNED (0 skips the second map), LEGSLAM_BENCH_PORTABLE (0 skips the portable
//! path where the CPU has a vector one: the fast path alone, e.g. for `perf record -D` past the
//! setup),
//! LEGSLAM_BENCH_SPARSE_ADAM (set: the mapper option `adam_sparse`; SLAM's default, and the
//! bench's, is dense Adam but for the features and SH), LEGSLAM_BENCH_DENSE_FEATURES (set: the
//! features dense too, `adam_sparse_features` false), LEGSLAM_BENCH_DENSE_SH (set: the SH dense
//! too, `adam_sparse_sh` false), LEGSLAM_BENCH_FEATURE_OFFSET (the mapper option
//! `feature_level_offset`, default 2: features at 80x60, as SLAM trains a 640-wide input),
//! LEGSLAM_BENCH_FEATURE_JITTER (the mapper option `feature_jitter`, default 1; 0 renders each
//! coarse pixel's block, as SLAM did with features at 160x120 before 2026-12-07),
//! LEGSLAM_BENCH_UNORDERED (1 adds a map grown without the mapper option `spatial_order`, on
//! the CPU's best path: compare it with that path's column).

#[path = "common/mod.rs"]
mod common;

use std::path::{Path, PathBuf};
use std::time::Instant;

use common::env;
use legslam_core::camera::{Intrinsics, Pose};
use legslam_core::map::{FeatureGrid, Mapper, MapperConfig};
use legslam_core::raster::{vector_paths, Simd};
use legslam_core::rng::Rng;
use legslam_core::Real;

const W: usize = 640;
const H: usize = 480;
const F: f64 = 585.0;

fn data_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/7scenes_tsdf_fusion/data")
}

/// Colour in [0, 1], depth in metres (0 invalid), camera-to-world pose of frame `i`.
fn frame(dir: &Path, i: usize) -> (Vec<Real>, Vec<Real>, Pose) {
    let stem = dir.join(format!("frame-{i:06}"));
    let rgb = image::open(stem.with_extension("color.jpg"))
        .expect("7-Scenes colour")
        .to_rgb8()
        .into_raw()
        .into_iter()
        .map(|v| v as Real / 255.0)
        .collect();
    let depth = image::open(stem.with_extension("depth.png"))
        .expect("7-Scenes depth")
        .to_luma16()
        .into_raw()
        .into_iter()
        .map(|v| match v {
            0 | 65535 => 0.0,
            v => v as Real / 1000.0,
        })
        .collect();
    let text = std::fs::read_to_string(stem.with_extension("pose.txt")).expect("7-Scenes pose");
    let v: Vec<f64> = text
        .split_whitespace()
        .map(|t| t.parse().unwrap())
        .collect();
    (rgb, depth, Pose::from_row_slice(&v[..16]))
}

/// A smooth unit-norm 16x16 grid of `k` channels: random values on a 4x4 grid, upsampled.
fn feature_grid(rng: &mut Rng, k: usize) -> FeatureGrid {
    let coarse: Vec<Real> = (0..16 * k).map(|_| rng.normal() as Real).collect();
    let coarse = FeatureGrid::new(coarse, 4, 4, k).unwrap();
    let mut data = coarse.upsample(16, 16);
    for f in data.chunks_exact_mut(k) {
        let n = f.iter().map(|v| v * v).sum::<Real>().sqrt().max(1e-6);
        f.iter_mut().for_each(|v| *v /= n);
    }
    FeatureGrid::new(data, 16, 16, k).unwrap()
}

fn main() {
    let dir = data_dir();
    if !dir.is_dir() {
        eprintln!("no 7-Scenes data at {}: nothing to measure", dir.display());
        return;
    }
    let k = env("LEGSLAM_BENCH_K", 64);
    let setup_iters = env("LEGSLAM_BENCH_SETUP_ITERS", 10);
    let iters = env("LEGSLAM_BENCH_ITERS", 20);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let mut config = MapperConfig {
        levels: 4,
        sh_degree: 3,
        num_features: k,
        feature_level_offset: env("LEGSLAM_BENCH_FEATURE_OFFSET", 2),
        feature_jitter: env("LEGSLAM_BENCH_FEATURE_JITTER", 1) != 0,
        ..Default::default()
    };
    config.grow.stride = 2;
    config.adam.sparse = std::env::var("LEGSLAM_BENCH_SPARSE_ADAM").is_ok();
    config.adam.sparse_features = std::env::var("LEGSLAM_BENCH_DENSE_FEATURES").is_err();
    config.adam.sparse_sh = std::env::var("LEGSLAM_BENCH_DENSE_SH").is_err();
    let grow = |config: MapperConfig| {
        let mut mapper = Mapper::new(config).unwrap();
        let intr = Intrinsics::from_array([F, F, 320.0, 240.0], W, H);
        let mut rng = Rng::new(1);
        let t = Instant::now();
        pool.install(|| {
            for i in (0..1000).step_by(12) {
                let (rgb, depth, pose) = frame(&dir, i);
                let (id, _) = mapper.add_keyframe(rgb, depth, intr, pose).unwrap();
                if k > 0 {
                    mapper.set_features(id, feature_grid(&mut rng, k)).unwrap();
                }
                mapper.train(setup_iters).unwrap();
            }
        });
        // The newest keyframes still train at coarser levels (each climbs down a level every
        // `uses_per_level` uses): trained on until every keyframe is at the finest, so that
        // every timed iteration is one at 320x240 (a median over both kinds was up to 25% low).
        let finest = mapper.config.finest_level;
        let at_finest =
            |m: &Mapper| (0..m.keyframes.len()).all(|ki| m.training_level(ki) <= finest);
        let mut warm = 0;
        pool.install(|| {
            while !at_finest(&mapper) && warm < 1000 {
                mapper.train(1).unwrap();
                warm += 1;
            }
        });
        assert!(
            at_finest(&mapper),
            "keyframes still coarse after {warm} iterations"
        );
        eprintln!(
            "map: {} Gaussians, {} keyframes, grown in {:.0} s (the last {warm} iterations \
             until every keyframe trains at its finest level)",
            mapper.map.len(),
            mapper.keyframes.len(),
            t.elapsed().as_secs_f64()
        );
        mapper
    };
    // The map with the portable and each of the CPU's vector paths (AVX2, AVX-512 or NEON: the
    // same bits, so alternating them trains the map as any one would), and one grown with
    // pruning by contribution at 1.6 per million of the view, half a 640x480 pixel
    // (LEGSLAM_BENCH_PRUNED=0 skips it), on the CPU's best path.
    let vectors = vector_paths();
    let mut mappers = vec![grow(config.clone())];
    let mut variants: Vec<(&str, usize, Simd)> = Vec::new();
    if env("LEGSLAM_BENCH_PORTABLE", 1) != 0 || vectors.is_empty() {
        variants.push(("portable", 0, Simd::Portable));
    }
    for &simd in &vectors {
        variants.push((simd.name(), 0, simd));
    }
    if env("LEGSLAM_BENCH_PRUNED", 1) != 0 {
        let mut pruned = config.clone();
        pruned.prune.min_contribution = 1.6;
        mappers.push(grow(pruned));
        variants.push(("pruned", mappers.len() - 1, Simd::Auto));
    }
    if env("LEGSLAM_BENCH_UNORDERED", 0) != 0 {
        let mut unordered = config.clone();
        unordered.spatial_order = false;
        mappers.push(grow(unordered));
        variants.push(("unordered", mappers.len() - 1, Simd::Auto));
    }
    let mut phases = vec![[(); 6].map(|_| Vec::new()); variants.len()];
    // An iteration's cost drifts as training goes on (the last keyframes climb from coarse
    // levels to the finest), so a second map steps as often as the first, which takes one
    // iteration per variant a round: its timed iteration is then the same iteration of
    // training as the first map's last variant's (the CPU's best path).
    let on_first = variants.iter().filter(|v| v.1 == 0).count();
    pool.install(|| {
        for _ in 0..iters {
            for (&(_, m, simd), times) in variants.iter().zip(&mut phases) {
                let mapper = &mut mappers[m];
                mapper.config.simd = simd;
                if m > 0 {
                    mapper.train(on_first - 1).unwrap();
                }
                let (t, cpu) = (Instant::now(), common::cpu_ms());
                let r = mapper.train(1).unwrap();
                let total = t.elapsed().as_secs_f64();
                let cpu = 1e-3 * (common::cpu_ms() - cpu);
                let all = [total, cpu, r.render_s, r.loss_s, r.backward_s, r.step_s];
                for (p, v) in times.iter_mut().zip(all) {
                    p.push(1e3 * v);
                }
            }
        }
    });
    let sizes: Vec<String> = mappers.iter().map(|m| m.map.len().to_string()).collect();
    println!(
        "mapper iteration, {} Gaussians, K = {k}, 2 threads, median of {iters} (ms; ratio to {}):",
        sizes.join(" / "),
        variants[0].0
    );
    let medians: Vec<Vec<f64>> = phases
        .iter()
        .map(|p| p.iter().map(|v| common::median(v.clone())).collect())
        .collect();
    for (i, name) in ["total", "cpu", "render", "loss", "backward", "step"]
        .iter()
        .enumerate()
    {
        let cells: Vec<String> = variants
            .iter()
            .zip(&medians)
            .map(|((v, _, _), m)| format!("{v} {:7.1} (x{:.2})", m[i], medians[0][i] / m[i]))
            .collect();
        println!("  {name:<9} {}", cells.join("   "));
    }
}
