//! A small harness for benchmarks that compare implementations: the variants of a case run
//! alternately, sample by sample, so that a machine whose speed drifts (a shared machine
//! swings by up to ~1.4x from hour to hour) slows them alike; medians and ratios are printed.

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

fn median(mut v: Vec<f64>) -> f64 {
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
    for v in variants.iter_mut() {
        (v.run)();
    }
    let mut times = vec![Vec::with_capacity(samples); variants.len()];
    for _ in 0..samples {
        for (v, t) in variants.iter_mut().zip(&mut times) {
            let start = Instant::now();
            (v.run)();
            t.push(1e3 * start.elapsed().as_secs_f64());
        }
    }
    let medians: Vec<f64> = times.into_iter().map(median).collect();
    let cells: Vec<String> = variants
        .iter()
        .zip(&medians)
        .map(|(v, m)| format!("{} {:8.1} ms (x{:.2})", v.name, m, medians[0] / m))
        .collect();
    println!("{case:<28} {}", cells.join("   "));
    medians
}

/// Samples per case: `LEGSLAM_BENCH_SAMPLES`, else `default`.
pub fn samples(default: usize) -> usize {
    std::env::var("LEGSLAM_BENCH_SAMPLES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Whether `case` contains `LEGSLAM_BENCH_FILTER` (every case when it is unset).
pub fn selected(case: &str) -> bool {
    std::env::var("LEGSLAM_BENCH_FILTER").map_or(true, |f| case.contains(&f))
}
