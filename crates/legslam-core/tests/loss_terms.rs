//! L1, depth L1, feature cosine and the combined loss: values against plain loops, gradients
//! against finite differences.

mod common;

use common::Rng;
use legslam_core::loss::{
    cosine, depth_l1, l1, Blend, DepthInputs, FeatureInputs, FeatureTarget, Loss, LossGrads,
    LossInputs, LossWeights, Ssim, COS_EPS,
};
use legslam_core::Real;

fn random(rng: &mut Rng, n: usize, a: f64, b: f64) -> Vec<Real> {
    (0..n).map(|_| rng.uniform(a, b) as Real).collect()
}

/// Central differences of `f` at `x` along each coordinate, compared with `grad`. f64 only:
/// in f32 the differences of means over many pixels are rounding noise.
#[cfg(feature = "f64")]
fn check_fd(x: &[Real], grad: &[Real], mut f: impl FnMut(&[Real]) -> f64, what: &str) {
    let h = 1e-6;
    for i in 0..x.len() {
        let (mut xp, mut xm) = (x.to_vec(), x.to_vec());
        xp[i] += h;
        xm[i] -= h;
        let fd = (f(&xp) - f(&xm)) / (2.0 * h);
        let g = grad[i];
        assert!(
            (fd - g).abs() < 1e-8 + 1e-6 * g.abs(),
            "{what} entry {i}: analytic {g} vs finite difference {fd}"
        );
    }
}

#[test]
fn l1_is_the_mean_absolute_error_over_masked_pixels() {
    let mut rng = Rng::new(10);
    let (r, t) = (
        random(&mut rng, 30, 0.0, 1.0),
        random(&mut rng, 30, 0.0, 1.0),
    );
    let mask: Vec<bool> = (0..10).map(|p| p % 3 != 0).collect();
    let mut g = vec![9.0; 30];
    let v = l1(&r, &t, Some(&mask), 3, &mut g).unwrap();
    let counted = mask.iter().filter(|&&m| m).count() * 3;
    let mut want = 0.0;
    for (p, &counts) in mask.iter().enumerate() {
        for c in 0..3 {
            let i = p * 3 + c;
            let d = (r[i] - t[i]) as f64;
            let expect = if counts {
                d.signum() / counted as f64
            } else {
                0.0
            };
            if counts {
                want += d.abs();
            }
            assert!((g[i] as f64 - expect).abs() < 1e-7, "{i}");
        }
    }
    assert!((v - want / counted as f64).abs() < 1e-6);
    // Unmasked, equal values: gradient 0 there; nothing counted: 0.
    let mut g = vec![9.0; 3];
    assert_eq!(l1(&[0.5; 3], &[0.5; 3], None, 3, &mut g).unwrap(), 0.0);
    assert_eq!(g, [0.0; 3]);
    assert_eq!(
        l1(&r, &t, Some(&[false; 10]), 3, &mut [0.0; 30]).unwrap(),
        0.0
    );
}

#[test]
fn depth_l1_counts_only_valid_targets() {
    let r = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
    let t = [1.5, 0.0, Real::NAN, -1.0, Real::INFINITY, 7.0];
    let mut g = [9.0; 6];
    let v = depth_l1(&r, &t, &mut g).unwrap();
    assert!((v - 0.75).abs() < 1e-7);
    assert_eq!(g, [-0.5, 0.0, 0.0, 0.0, 0.0, -0.5]);
    let v = depth_l1(&r, &[0.0; 6], &mut g).unwrap();
    assert_eq!((v, g), (0.0, [0.0; 6]));
}

/// Whole images, unmasked, whose pixel counts the terms split into runs of different lengths
/// (256, 37 and 1 pixels), against plain loops.
#[test]
fn l1_terms_over_images_match_plain_loops() {
    let mut rng = Rng::new(16);
    for pixels in [512 * 3, 37 * 23, 211] {
        let n = pixels * 3;
        let (r, t) = (random(&mut rng, n, 0.0, 1.0), random(&mut rng, n, 0.0, 1.0));
        let mut g = vec![9.0; n];
        let v = l1(&r, &t, None, 3, &mut g).unwrap();
        let want: f64 = r.iter().zip(&t).map(|(a, b)| (a - b).abs() as f64).sum();
        assert!((v - want / n as f64).abs() < 1e-6, "{pixels}: {v}");
        for i in 0..n {
            let expect = (r[i] - t[i]).signum() as f64 / n as f64;
            assert!((g[i] as f64 - expect).abs() < 1e-9, "{pixels}: colour {i}");
        }
        // Depth with every fifth target invalid (0, NaN, negative or infinite in turn).
        let (r, mut t) = (
            random(&mut rng, pixels, 0.5, 3.0),
            random(&mut rng, pixels, 0.5, 3.0),
        );
        for (i, z) in t.iter_mut().enumerate().filter(|(i, _)| i % 5 == 2) {
            *z = [0.0, Real::NAN, -1.0, Real::INFINITY][i / 5 % 4];
        }
        let valid: Vec<bool> = t.iter().map(|z| *z > 0.0 && z.is_finite()).collect();
        let counted = valid.iter().filter(|&&v| v).count();
        let mut g = vec![9.0; pixels];
        let v = depth_l1(&r, &t, &mut g).unwrap();
        let want: f64 = (0..pixels)
            .filter(|&i| valid[i])
            .map(|i| (r[i] - t[i]).abs() as f64)
            .sum();
        assert!((v - want / counted as f64).abs() < 1e-6, "{pixels}: {v}");
        for i in 0..pixels {
            let expect = if valid[i] {
                (r[i] - t[i]).signum() as f64 / counted as f64
            } else {
                0.0
            };
            assert!((g[i] as f64 - expect).abs() < 1e-9, "{pixels}: depth {i}");
        }
    }
}

#[test]
fn cosine_value_and_clamped_gradient() {
    // Orthogonal: 1 - 0; parallel: 1 - 1; a zero rendered vector: cos 0 and gradient
    // -t / (eps |t|) / pixels.
    let r = [1.0, 0.0, 2.0, 0.0, 0.0, 0.0];
    let t = [0.0, 3.0, 5.0, 0.0, 0.0, 2.0];
    let mut g = [0.0; 6];
    let v = cosine(&r, &t, 2, None, &mut g).unwrap();
    assert!((v - 2.0 / 3.0).abs() < 1e-6);
    assert!((g[4] - 0.0).abs() < 1e-6);
    let want = -1.0 / (COS_EPS as f64 * 3.0);
    assert!(
        ((g[5] as f64) / want - 1.0).abs() < 1e-5,
        "{} vs {want}",
        g[5]
    );
    // Parallel vectors are a minimum: zero gradient.
    assert!(g[2].abs() < 1e-6 && g[3].abs() < 1e-6);
    let v = cosine(&r, &t, 2, Some(&[false, true, false]), &mut g).unwrap();
    assert!(v.abs() < 1e-6 && g[0] == 0.0 && g[5] == 0.0);
}

#[cfg(feature = "f64")]
#[test]
fn term_gradients_match_finite_differences() {
    let mut rng = Rng::new(11);
    let (r, t) = (
        random(&mut rng, 60, 0.0, 1.0),
        random(&mut rng, 60, 0.0, 1.0),
    );
    let mask: Vec<bool> = (0..20).map(|p| p % 4 != 1).collect();
    let mut g = vec![0.0; 60];
    l1(&r, &t, Some(&mask), 3, &mut g).unwrap();
    check_fd(
        &r,
        &g,
        |x| l1(x, &t, Some(&mask), 3, &mut vec![0.0; 60]).unwrap(),
        "l1",
    );
    let mut td = t.clone();
    td[3] = 0.0;
    depth_l1(&r, &td, &mut g).unwrap();
    check_fd(
        &r,
        &g,
        |x| depth_l1(x, &td, &mut vec![0.0; 60]).unwrap(),
        "depth",
    );
    let (r, t) = (
        random(&mut rng, 60, -1.0, 1.0),
        random(&mut rng, 60, -1.0, 1.0),
    );
    cosine(&r, &t, 6, Some(&mask[..10]), &mut g).unwrap();
    check_fd(
        &r,
        &g,
        |x| cosine(x, &t, 6, Some(&mask[..10]), &mut vec![0.0; 60]).unwrap(),
        "cos",
    );
}

struct Case {
    w: usize,
    h: usize,
    color: Vec<Real>,
    target_color: Vec<Real>,
    mask: Vec<bool>,
    depth: Vec<Real>,
    target_depth: Vec<Real>,
    feat: Vec<Real>,
    target_feat: Vec<Real>,
    k: usize,
}

impl Case {
    fn new(seed: u64) -> Self {
        let mut rng = Rng::new(seed);
        let (w, h, k) = (14, 12, 5);
        let n = w * h;
        let mut target_depth = random(&mut rng, n, 0.5, 3.0);
        target_depth.iter_mut().step_by(7).for_each(|z| *z = 0.0);
        Case {
            w,
            h,
            color: random(&mut rng, n * 3, 0.0, 1.0),
            target_color: random(&mut rng, n * 3, 0.0, 1.0),
            mask: (0..n).map(|p| p % 5 != 0).collect(),
            depth: random(&mut rng, n, 0.5, 3.0),
            target_depth,
            // Features at half resolution, as the caller may render them.
            feat: random(&mut rng, n / 4 * k, -1.0, 1.0),
            target_feat: random(&mut rng, n / 4 * k, -1.0, 1.0),
            k,
        }
    }

    fn inputs<'a>(&'a self, color: &'a [Real]) -> LossInputs<'a> {
        LossInputs {
            width: self.w,
            height: self.h,
            color,
            target_color: &self.target_color,
            color_mask: Some(&self.mask),
            depth: Some(DepthInputs {
                rendered: &self.depth,
                target: &self.target_depth,
            }),
            features: Some(FeatureInputs {
                rendered: &self.feat,
                target: FeatureTarget::Pixels(&self.target_feat),
                channels: self.k,
                mask: None,
            }),
        }
    }

    fn eval(&self, loss: &mut Loss, color: &[Real]) -> (f64, Vec<Real>, Vec<Real>, Vec<Real>) {
        let (mut gc, mut gd, mut gf) = (
            vec![7.0; color.len()],
            vec![7.0; self.depth.len()],
            vec![7.0; self.feat.len()],
        );
        let grads = LossGrads {
            color: &mut gc,
            depth: Some(&mut gd),
            features: Some(&mut gf),
        };
        let t = loss.evaluate(&self.inputs(color), grads).unwrap();
        (t.total, gc, gd, gf)
    }
}

#[test]
fn combined_loss_is_the_weighted_sum_of_its_terms() {
    let c = Case::new(12);
    let weights = LossWeights {
        color: 0.7,
        ssim_lambda: 0.3,
        depth: 0.4,
        feature: 0.2,
    };
    let mut loss = Loss::new(weights);
    let (total, gc, gd, gf) = c.eval(&mut loss, &c.color);
    let n = c.color.len();
    let (mut g1, mut gs, mut gd2, mut gf2) = (
        vec![0.0; n],
        vec![0.0; n],
        vec![0.0; gd.len()],
        vec![0.0; gf.len()],
    );
    let v1 = l1(&c.color, &c.target_color, Some(&c.mask), 3, &mut g1).unwrap();
    let vs = Ssim::new()
        .value_and_grad(&c.color, &c.target_color, c.w, c.h, 3, &mut gs)
        .unwrap();
    let vd = depth_l1(&c.depth, &c.target_depth, &mut gd2).unwrap();
    let vf = cosine(&c.feat, &c.target_feat, c.k, None, &mut gf2).unwrap();
    let want = 0.7 * (0.7 * v1 + 0.3 * (1.0 - vs)) + 0.4 * vd + 0.2 * vf;
    assert!((total - want).abs() < 1e-6, "{total} vs {want}");
    for i in 0..n {
        let want = 0.7 * (0.7 * g1[i] - 0.3 * gs[i]);
        assert!((gc[i] - want).abs() < 1e-6, "colour {i}");
    }
    for (a, b) in gd.iter().zip(&gd2) {
        assert!((a - 0.4 * b).abs() < 1e-6);
    }
    for (a, b) in gf.iter().zip(&gf2) {
        assert!((a - 0.2 * b).abs() < 1e-6);
    }
}

/// A blended target is read as the per-pixel target it expands to: the same loss, and the
/// same gradients bit for bit (with a mask, and with rows blended in either order).
#[test]
fn blended_feature_target_is_its_expansion() {
    let mut rng = Rng::new(15);
    let (w, h, k, rows_n) = (7, 5, 6, 3);
    let rows = random(&mut rng, rows_n * w * k, -1.0, 1.0);
    let blends: Vec<Blend> = (0..h)
        .map(|y| Blend {
            lower: y % rows_n,
            upper: (y * 2 + 1) % rows_n,
            weight: [0.0, 0.3, 1.0, 0.75, 0.5][y],
        })
        .collect();
    let expanded: Vec<Real> = (0..h)
        .flat_map(|y| {
            let b = blends[y];
            let (lo, hi) = (
                &rows[b.lower * w * k..][..w * k],
                &rows[b.upper * w * k..][..w * k],
            );
            let v: Vec<Real> = lo
                .iter()
                .zip(hi)
                .map(|(l, h)| l + b.weight * (h - l))
                .collect();
            v
        })
        .collect();
    let rendered = random(&mut rng, w * h * k, -1.0, 1.0);
    let mask: Vec<bool> = (0..w * h).map(|p| p % 4 != 1).collect();
    let mut loss = Loss::default();
    let mut eval = |target: FeatureTarget| {
        let (mut gc, mut gf) = (vec![0.0; w * h * 3], vec![7.0; w * h * k]);
        let color = vec![0.5; w * h * 3];
        let inputs = LossInputs {
            width: w,
            height: h,
            color: &color,
            target_color: &color,
            color_mask: None,
            depth: None,
            features: Some(FeatureInputs {
                rendered: &rendered,
                target,
                channels: k,
                mask: Some(&mask),
            }),
        };
        let grads = LossGrads {
            color: &mut gc,
            depth: None,
            features: Some(&mut gf),
        };
        let t = loss.evaluate(&inputs, grads).map(|t| t.feature);
        (t, gf)
    };
    let (want, want_g) = eval(FeatureTarget::Pixels(&expanded));
    let blended = FeatureTarget::Blended {
        rows: &rows,
        blends: &blends,
    };
    let (got, got_g) = eval(blended);
    let (got, want) = (got.unwrap(), want.unwrap());
    // The pixels' terms are the same; a per-pixel target is summed in other runs of pixels.
    assert!(want > 0.1 && (got - want).abs() < 1e-12, "{got} vs {want}");
    let bits = |v: &[Real]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&got_g), bits(&want_g));
    // Rows that do not fit, blends that reach past the rows or weigh outside [0, 1].
    let mut bad = |rows: &[Real], blends: &[Blend]| eval(FeatureTarget::Blended { rows, blends }).0;
    assert!(bad(&rows[1..], &blends).unwrap_err().contains("rows"));
    assert!(bad(&rows, &blends[1..])
        .unwrap_err()
        .contains("cannot cover"));
    let mut out_of_range = blends.clone();
    out_of_range[2].upper = rows_n;
    assert!(bad(&rows, &out_of_range)
        .unwrap_err()
        .contains("out of range"));
    out_of_range[2] = Blend {
        weight: 1.5,
        ..blends[2]
    };
    assert!(bad(&rows, &out_of_range)
        .unwrap_err()
        .contains("out of range"));
}

#[cfg(feature = "f64")]
#[test]
fn combined_colour_gradient_matches_finite_differences() {
    let c = Case::new(13);
    let mut loss = Loss::new(LossWeights::default());
    let (_, gc, _, _) = c.eval(&mut loss, &c.color);
    check_fd(&c.color, &gc, |x| c.eval(&mut loss, x).0, "combined colour");
}

#[test]
fn absent_terms_and_bad_sizes() {
    let c = Case::new(14);
    let mut loss = Loss::default();
    let mut gc = vec![0.0; c.color.len()];
    let mut inputs = c.inputs(&c.color);
    inputs.depth = None;
    inputs.features = None;
    let grads = LossGrads {
        color: &mut gc,
        depth: None,
        features: None,
    };
    let t = loss.evaluate(&inputs, grads).unwrap();
    assert_eq!((t.depth_l1, t.feature), (0.0, 0.0));
    let mut gd = vec![0.0; c.depth.len()];
    let grads = LossGrads {
        color: &mut gc,
        depth: Some(&mut gd),
        features: None,
    };
    assert!(loss.evaluate(&inputs, grads).unwrap_err().contains("depth"));
    let mut inputs = c.inputs(&c.color[1..]);
    inputs.depth = None;
    inputs.features = None;
    let grads = LossGrads {
        color: &mut gc,
        depth: None,
        features: None,
    };
    assert!(loss
        .evaluate(&inputs, grads)
        .unwrap_err()
        .contains("rendered colour"));
    let mut g = vec![0.0; 10];
    assert!(cosine(&[0.0; 10], &[0.0; 10], 3, None, &mut g).is_err());
    assert!(
        cosine(&[0.0; 9], &[0.0; 9], 3, Some(&[true; 2]), &mut g[..9])
            .unwrap_err()
            .contains("mask")
    );
    assert!(depth_l1(&[0.0; 3], &[0.0; 4], &mut g[..3]).is_err());
}
