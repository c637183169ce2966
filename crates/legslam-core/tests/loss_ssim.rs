//! SSIM: the separable fast path against a direct 2-D windowed reference, against
//! scikit-image, and its gradient against finite differences.

mod common;

use common::Rng;
use legslam_core::loss::Ssim;
use legslam_core::Real;

/// Direct definition: per pixel and channel, 11x11 Gaussian-weighted sums (sigma 1.5, the 2-D
/// window the outer product of the normalised 1-D one) over the pixels inside the image
/// (zero padding), in f64.
fn reference_ssim(x: &[Real], y: &[Real], w: usize, h: usize, c: usize) -> f64 {
    let g: Vec<f64> = (-5i64..=5).map(|d| (-(d * d) as f64 / 4.5).exp()).collect();
    let total: f64 = g.iter().sum();
    let (c1, c2) = (1e-4, 9e-4);
    let mut sum = 0.0;
    for r in 0..h as i64 {
        for col in 0..w as i64 {
            for ch in 0..c {
                let (mut mx, mut my, mut exx, mut eyy, mut exy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for dr in -5i64..=5 {
                    for dc in -5i64..=5 {
                        let (rr, cc) = (r + dr, col + dc);
                        if rr < 0 || cc < 0 || rr >= h as i64 || cc >= w as i64 {
                            continue;
                        }
                        let wt = g[(dr + 5) as usize] * g[(dc + 5) as usize] / (total * total);
                        let i = (rr as usize * w + cc as usize) * c + ch;
                        let (a, b) = (x[i] as f64, y[i] as f64);
                        mx += wt * a;
                        my += wt * b;
                        exx += wt * a * a;
                        eyy += wt * b * b;
                        exy += wt * a * b;
                    }
                }
                let (sxx, syy, sxy) = (exx - mx * mx, eyy - my * my, exy - mx * my);
                sum += (2.0 * mx * my + c1) * (2.0 * sxy + c2)
                    / ((mx * mx + my * my + c1) * (sxx + syy + c2));
            }
        }
    }
    sum / (w * h * c) as f64
}

/// A random image in [0, 1] and a noisy copy of it, so SSIM is neither 0 nor 1.
fn pair(rng: &mut Rng, n: usize) -> (Vec<Real>, Vec<Real>) {
    let x: Vec<Real> = (0..n).map(|_| rng.next_f64() as Real).collect();
    let y = x
        .iter()
        .map(|&v| (v as f64 + 0.3 * rng.normal()).clamp(0.0, 1.0) as Real)
        .collect();
    (x, y)
}

#[cfg(feature = "f64")]
const VALUE_TOL: f64 = 1e-12;
// f32: E[x^2] - mu^2 cancels; values in [0,1] leave ~1e-6 absolute error per pixel.
#[cfg(not(feature = "f64"))]
const VALUE_TOL: f64 = 2e-5;

#[test]
fn fast_matches_direct_reference_on_random_images() {
    let mut rng = Rng::new(1);
    let mut ssim = Ssim::new();
    for (w, h, c) in [
        (1, 1, 1),
        (3, 2, 1),
        (7, 4, 3),
        (12, 17, 1),
        (33, 20, 3),
        (64, 48, 3),
    ] {
        let (x, y) = pair(&mut rng, w * h * c);
        let fast = ssim.value(&x, &y, w, h, c).unwrap();
        let slow = reference_ssim(&x, &y, w, h, c);
        assert!(
            (fast - slow).abs() < VALUE_TOL,
            "{w}x{h}x{c}: fast {fast} vs reference {slow}"
        );
        let mut grad = vec![0.0; x.len()];
        let with_grad = ssim.value_and_grad(&x, &y, w, h, c, &mut grad).unwrap();
        assert_eq!(fast, with_grad);
    }
}

#[test]
fn identical_images_give_one_and_zero_gradient() {
    let mut rng = Rng::new(2);
    let (x, _) = pair(&mut rng, 20 * 15 * 3);
    let mut grad = vec![1.0; x.len()];
    let s = Ssim::new()
        .value_and_grad(&x, &x, 20, 15, 3, &mut grad)
        .unwrap();
    assert!((s - 1.0).abs() < 1e-5, "{s}");
    let worst = grad.iter().fold(0.0 as Real, |m, g| m.max(g.abs()));
    assert!(worst < 1e-6, "largest gradient {worst}");
}

/// scikit-image 0.26 `structural_similarity(x, y, channel_axis=-1, gaussian_weights=True,
/// sigma=1.5, use_sample_covariance=False, data_range=1.0)` on the image below (computed in
/// Python from the same integer formula). skimage reflects at the border and then crops 5
/// pixels; the image is zero in a 10-pixel band, so every pixel within 5 of an edge has an
/// all-zero window and SSIM exactly 1 under zero padding. Removing those recovers the mean over
/// skimage's interior, where the two border rules agree.
#[test]
fn matches_scikit_image_on_the_interior() {
    const SKIMAGE: f64 = 0.9058617420537897;
    let (w, h, c) = (64, 48, 3);
    let (mut x, mut y) = (vec![0.0; w * h * c], vec![0.0; w * h * c]);
    for r in 10..h - 10 {
        for col in 10..w - 10 {
            for ch in 0..c {
                let i = (r * w + col) * c + ch;
                let xi = (i * 7919 + (i * i) % 104729) % 1000;
                let yi = (xi as i64 + ((i * 31) % 601) as i64 - 300).clamp(0, 1000);
                x[i] = xi as Real / 1000.0;
                y[i] = yi as Real / 1000.0;
            }
        }
    }
    let full = Ssim::new().value(&x, &y, w, h, c).unwrap();
    let interior = (h - 10) * (w - 10);
    let border = w * h - interior;
    let interior_mean = (full * (w * h) as f64 - border as f64) / interior as f64;
    assert!(
        (interior_mean - SKIMAGE).abs() < 1e-5,
        "{interior_mean} vs scikit-image {SKIMAGE}"
    );
}

/// Checks d(SSIM)/d(x) against central differences. f64: every entry with h = 1e-6. f32:
/// the cancellation in E[x^2] - mu^2 leaves ~1e-7 noise on SSIM, so only a directional
/// derivative with a large step is meaningful there.
#[test]
fn gradient_matches_finite_differences() {
    let mut rng = Rng::new(3);
    let (w, h, c) = (13, 11, 3);
    let (x, y) = pair(&mut rng, w * h * c);
    let mut ssim = Ssim::new();
    let mut grad = vec![0.0; x.len()];
    ssim.value_and_grad(&x, &y, w, h, c, &mut grad).unwrap();
    let mut f = |x: &[Real]| ssim.value(x, &y, w, h, c).unwrap();
    if cfg!(feature = "f64") {
        let step = 1e-6;
        for i in 0..x.len() {
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[i] += step as Real;
            xm[i] -= step as Real;
            let fd = (f(&xp) - f(&xm)) / (2.0 * step);
            let g = grad[i] as f64;
            assert!(
                (fd - g).abs() < 1e-8 + 1e-6 * g.abs(),
                "entry {i}: analytic {g} vs finite difference {fd}"
            );
        }
    } else {
        let dir: Vec<Real> = (0..x.len()).map(|_| rng.normal() as Real).collect();
        let step = 1e-2;
        let shifted = |s: f64| -> Vec<Real> {
            x.iter()
                .zip(&dir)
                .map(|(&a, &d)| a + (s * d as f64) as Real)
                .collect()
        };
        let fd = (f(&shifted(step)) - f(&shifted(-step))) / (2.0 * step);
        let g: f64 = grad
            .iter()
            .zip(&dir)
            .map(|(&g, &d)| g as f64 * d as f64)
            .sum();
        assert!((fd - g).abs() < 2e-2 * g.abs() + 1e-5, "{g} vs {fd}");
    }
}

#[test]
fn same_bits_on_one_and_two_threads() {
    let mut rng = Rng::new(4);
    let (w, h, c) = (97, 61, 3);
    let (x, y) = pair(&mut rng, w * h * c);
    let run = |threads| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut grad = vec![0.0; x.len()];
            let s = Ssim::new()
                .value_and_grad(&x, &y, w, h, c, &mut grad)
                .unwrap();
            (
                s.to_bits(),
                grad.iter().map(|g| g.to_bits()).collect::<Vec<_>>(),
            )
        })
    };
    assert_eq!(run(1), run(2));
}

#[test]
fn bad_sizes_are_errors() {
    let mut ssim = Ssim::new();
    let x = vec![0.5; 12];
    let mut g = [0.0; 12];
    assert!(ssim
        .value(&x, &x, 2, 2, 2)
        .unwrap_err()
        .contains("SSIM rendered image"));
    assert!(ssim
        .value(&x, &x[..11], 2, 2, 3)
        .unwrap_err()
        .contains("target"));
    assert!(ssim
        .value_and_grad(&x, &x, 2, 2, 3, &mut g[..5])
        .unwrap_err()
        .contains("gradient"));
    assert!(ssim
        .value(&[], &[], 0, 4, 3)
        .unwrap_err()
        .contains("non-empty"));
}

/// The AVX2 build of the per-row loops gives the baseline's bits, value and gradient, on sizes
/// that leave vector tails of many lengths.
#[test]
fn the_avx2_loops_give_the_baseline_bits() {
    if !legslam_core::raster::avx2_available() {
        eprintln!("no AVX2 on this CPU: nothing to compare");
        return;
    }
    let mut rng = Rng::new(7);
    let (mut fast, mut plain) = (Ssim::with_avx2(true), Ssim::with_avx2(false));
    for (w, h, c) in [
        (1, 1, 1),
        (5, 3, 3),
        (13, 11, 1),
        (37, 23, 3),
        (160, 120, 3),
    ] {
        let (x, y) = pair(&mut rng, w * h * c);
        let (mut ga, mut gb) = (vec![0.0; x.len()], vec![0.0; x.len()]);
        let va = fast.value_and_grad(&x, &y, w, h, c, &mut ga).unwrap();
        let vb = plain.value_and_grad(&x, &y, w, h, c, &mut gb).unwrap();
        assert_eq!(va.to_bits(), vb.to_bits(), "{w}x{h}x{c}: value");
        let bits = |g: &[Real]| g.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&ga), bits(&gb), "{w}x{h}x{c}: gradient");
    }
}
