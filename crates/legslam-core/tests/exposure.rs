//! Keyframe exposure: its hand-written gradients against central finite differences (f64
//! builds), and training recovers a keyframe's brightness change without repainting the map.

use legslam_core::camera::{Intrinsics, Pose};
use legslam_core::map::{Mapper, MapperConfig};
use legslam_core::Real;

#[cfg(feature = "f64")]
/// L = sum (exposed - target)^2 / 2 and its gradient with respect to the exposed colour.
fn loss(
    e: &legslam_core::map::exposure::Exposure,
    color: &[Real],
    target: &[Real],
) -> (f64, Vec<Real>) {
    let mut out = Vec::new();
    e.apply(color, &mut out);
    let grad: Vec<Real> = out.iter().zip(target).map(|(o, t)| o - t).collect();
    let l = grad
        .iter()
        .map(|g| 0.5 * f64::from(*g) * f64::from(*g))
        .sum();
    (l, grad)
}

#[cfg(feature = "f64")]
#[test]
fn exposure_gradients_match_finite_differences() {
    let mut rng = legslam_core::rng::Rng::new(5);
    let n = 40 * 3;
    let color: Vec<Real> = (0..n).map(|_| rng.uniform(0.0, 1.0)).collect();
    let target: Vec<Real> = (0..n).map(|_| rng.uniform(0.0, 1.0)).collect();
    let mut e = legslam_core::map::exposure::Exposure::default();
    e.log_gain = [0.2, -0.1, 0.05];
    e.bias = [0.03, -0.02, 0.1];
    let (_, mut grad) = loss(&e, &color, &target);
    let params = e.backward(&color, &mut grad);
    let h = 1e-6;
    for k in 0..6 {
        let at = |d: f64| {
            let mut e2 = e.clone();
            if k < 3 {
                e2.log_gain[k] += d;
            } else {
                e2.bias[k - 3] += d;
            }
            loss(&e2, &color, &target).0
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        assert!(
            (fd - params[k]).abs() < 1e-6 * (1.0 + fd.abs()),
            "param {k}: {fd} vs {}",
            params[k]
        );
    }
    for p in [0, 7, 50, n - 1] {
        let at = |d: f64| {
            let mut c2 = color.clone();
            c2[p] += d;
            loss(&e, &c2, &target).0
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        assert!(
            (fd - grad[p]).abs() < 1e-6 * (1.0 + fd.abs()),
            "colour {p}: {fd} vs {}",
            grad[p]
        );
    }
}

/// A textured wall 2 m away (every channel varies), its colours scaled by `gain`.
fn wall(gain: Real) -> (Vec<Real>, Vec<Real>, Intrinsics) {
    let (w, h) = (48, 36);
    let mut rgb = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let check = ((x / 6 + y / 6) % 2) as Real;
            let (u, v) = (x as Real / w as Real, y as Real / h as Real);
            rgb.extend([0.2 + 0.4 * check, 0.3 + 0.3 * u, 0.2 + 0.3 * v].map(|c| c * gain));
        }
    }
    let depth = vec![2.0; w * h];
    let k = Intrinsics::from_array([50.0, 50.0, 23.5, 17.5], w, h);
    (rgb, depth, k)
}

/// Two keyframes of one wall, the second 30% brighter: with exposures trained, the second
/// keyframe's gain takes the change and the map keeps the first keyframe's colours; without,
/// the map settles between the two.
#[test]
fn a_brighter_keyframe_is_explained_by_its_exposure() {
    let run = |exposure_lr: Real| {
        let mut cfg = MapperConfig {
            finest_level: 0,
            grow_level: 0,
            exposure_lr,
            ..Default::default()
        };
        cfg.densify.interval = 0;
        let mut m = Mapper::new(cfg).unwrap();
        let (rgb, depth, k) = wall(1.0);
        m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
        let (rgb, depth, k) = wall(1.3);
        m.add_keyframe(rgb, depth, k, Pose::identity()).unwrap();
        m.train_window(400, 2).unwrap();
        let r = m.render(&Pose::identity(), k, true, false).unwrap();
        let (mean_render, mean_first) = {
            let (a, b) = (wall(1.0).0, &r.color);
            let n = a.len() as f64;
            (
                b.iter().map(|v| f64::from(*v)).sum::<f64>() / n,
                a.iter().map(|v| f64::from(*v)).sum::<f64>() / n,
            )
        };
        (m, mean_render / mean_first)
    };
    let (m, ratio) = run(0.01);
    assert!(
        m.keyframes[0].exposure.is_identity(),
        "the first keyframe's exposure moved"
    );
    let gain = m.keyframes[1].exposure.log_gain.map(Real::exp);
    for g in gain {
        assert!((g - 1.3).abs() < 0.08, "gain {gain:?}");
    }
    assert!(
        (ratio - 1.0).abs() < 0.02,
        "the map's brightness moved to {ratio}"
    );
    let (_, ratio_without) = run(0.0);
    assert!(
        ratio_without > 1.05,
        "without exposures the map stays at {ratio_without}"
    );
}
