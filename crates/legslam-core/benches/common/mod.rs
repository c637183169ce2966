//! A small harness for benchmarks that compare implementations: the variants of a case run
//! alternately, sample by sample, so that a machine whose speed drifts (a shared machine
//! swings by up to ~1.4x from hour to hour) slows them alike; medians and ratios are printed,
//! of wall time and of CPU time (all threads' time on a core: a loaded machine's waits for a
//! core do not count in it).

// Each bench uses the parts it needs.
#![allow(dead_code)]

use std::time::Instant;

/// One variant of a case: a name and what to time.
pub struct Variant<'a> {
    pub name: &'a str,
    pub run: Box<dyn FnMut() + 'a>,
}

pub fn variant<'a>(name: &'a str, run: impl FnMut() + 'a) -> Variant<'a> {
    Variant {
        name,
        run: Box::new(run),
    }
}

pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Runs every variant once to warm up, then `samples` rounds of one run each, in turn; prints
/// `case` with each variant's median in ms and its ratio to the first (the baseline). Returns
/// the medians.
pub fn compare(case: &str, samples: usize, variants: &mut [Variant]) -> Vec<f64> {
    if !selected(case) {
        return Vec::new();
    }
    // LEGSLAM_BENCH_VARIANT runs one variant alone (e.g. under a profiler).
    if let Ok(only) = std::env::var("LEGSLAM_BENCH_VARIANT") {
        for v in variants.iter_mut().filter(|v| v.name == only) {
            for _ in 0..samples.max(1) {
                (v.run)();
            }
        }
        return Vec::new();
    }
    for v in variants.iter_mut() {
        (v.run)();
    }
    let mut wall = vec![Vec::with_capacity(samples); variants.len()];
    let mut cpu = wall.clone();
    for _ in 0..samples {
        for ((v, w), c) in variants.iter_mut().zip(&mut wall).zip(&mut cpu) {
            let (start, cpu_start) = (Instant::now(), cpu_ms());
            (v.run)();
            w.push(1e3 * start.elapsed().as_secs_f64());
            c.push(cpu_ms() - cpu_start);
        }
    }
    let wall: Vec<f64> = wall.into_iter().map(median).collect();
    let cpu: Vec<f64> = cpu.into_iter().map(median).collect();
    let cells: Vec<String> = variants
        .iter()
        .enumerate()
        .map(|(i, v)| {
            format!(
                "{} {:7.1} ms (x{:.2}), cpu {:7.1} ms (x{:.2})",
                v.name,
                wall[i],
                wall[0] / wall[i],
                cpu[i],
                cpu[0] / cpu[i]
            )
        })
        .collect();
    println!("{case:<24} {}", cells.join("   "));
    wall
}

/// CPU time of every thread of this process so far, in ms (Linux; 0 elsewhere).
pub fn cpu_ms() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    tasks
        .flatten()
        .filter_map(|t| std::fs::read_to_string(t.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .sum::<f64>()
        / 1e6
}

/// The environment variable `name` as a number, else `default`.
pub fn env(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Samples per case: `LEGSLAM_BENCH_SAMPLES`, else `default`.
pub fn samples(default: usize) -> usize {
    env("LEGSLAM_BENCH_SAMPLES", default)
}

/// Whether `case` contains `LEGSLAM_BENCH_FILTER` (every case when it is unset).
pub fn selected(case: &str) -> bool {
    std::env::var("LEGSLAM_BENCH_FILTER").map_or(true, |f| case.contains(&f))
}
