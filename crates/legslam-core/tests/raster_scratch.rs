//! The render and the backward pass with buffers reused across calls against fresh buffers:
//! a reused render's images are a fresh one's whatever the last render left in them, and
//! nothing of one backward pass may leak into the rows of the next that it lists as on screen,
//! whatever the sizes and whichever Gaussians are on screen (the other rows are not read: zero
//! in fresh buffers, whatever the last pass left in reused ones).

mod common;

use common::{random_scene, Rng};
use legslam_core::raster::{
    backward, backward_into, render, render_into, BackwardScratch, Gradients, ImageGrads,
    RenderOptions, Rendered,
};
use legslam_core::Real;

#[test]
fn reused_buffers_give_what_fresh_ones_give() {
    let mut scratch = BackwardScratch::default();
    let mut out = Gradients::default();
    // Large, then smaller, then without features, then larger again; then the same Gaussians
    // seen from three cameras that each see some of them (rows the last view wrote are now off
    // screen, or on screen again).
    let mut scenes: Vec<_> = [
        (1, 400, 64, 48, 6),
        (2, 50, 32, 24, 6),
        (3, 200, 48, 40, 0),
        (4, 600, 80, 60, 3),
        // A few Gaussians, features in a coarser layer: most tiles have nothing to composite.
        (5, 3, 64, 48, 4),
    ]
    .into_iter()
    .map(|(seed, n, w, h, k)| (seed, random_scene(seed, n, w, h, 1, k)))
    .collect();
    let base = random_scene(5, 500, 64, 48, 1, 4);
    for (i, shift) in [0.0, 0.6, -0.6].into_iter().enumerate() {
        let mut s = base.clone();
        s.w2c[(0, 3)] += shift;
        scenes.push((6 + i as u64, s));
    }
    let mut visible = Vec::new();
    // Features alternate between the main layer and a coarser one of their own.
    let mut reused = Rendered::default();
    for (seed, s) in scenes {
        let (w, h, k) = (s.intr.width, s.intr.height, s.k);
        let opts = RenderOptions {
            sh_degree: 1,
            feature_scale: 1 + seed as usize % 2,
            ..Default::default()
        };
        let r = render(&s.gaussians(), &s.camera(), &opts).unwrap();
        // The reused render keeps its falloffs for the backward pass, but for one scene (whose
        // backward must then ignore those the last render left).
        let kept = RenderOptions {
            for_backward: seed != 3,
            ..opts
        };
        // What the last render left is poisoned: a pixel the compositing did not write would
        // keep a NaN, which equals nothing.
        for v in [
            &mut reused.color,
            &mut reused.depth,
            &mut reused.alpha,
            &mut reused.features,
        ] {
            v.fill(Real::NAN);
        }
        render_into(&s.gaussians(), &s.camera(), &kept, &mut reused).unwrap();
        assert_eq!(
            (&r.color, &r.depth, &r.alpha, &r.features),
            (
                &reused.color,
                &reused.depth,
                &reused.alpha,
                &reused.features
            ),
            "scene {seed}: a reused render"
        );
        let mut rng = Rng::new(seed + 100);
        let mut noise = |len: usize| -> Vec<_> { (0..len).map(|_| rng.normal() as _).collect() };
        let feature_pix = r.feature_width * r.feature_height;
        let (dc, dd, df) = (noise(w * h * 3), noise(w * h), noise(feature_pix * k));
        let grads = ImageGrads {
            color: Some(&dc),
            depth: Some(&dd),
            alpha: None,
            features: (k > 0).then_some(&df[..]),
        };
        let mut fresh = backward(&s.gaussians(), &s.camera(), &r, &grads).unwrap();
        backward_into(
            &s.gaussians(),
            &s.camera(),
            &reused,
            &grads,
            &mut scratch,
            &mut out,
        )
        .unwrap();
        assert!(
            fresh.means.iter().any(|v| *v != 0.0),
            "scene {seed} has no gradient at all"
        );
        assert_eq!(fresh.rows, out.rows, "scene {seed}");
        let n = s.gaussians().len();
        let on_screen = fresh.rows.clone();
        let arrays = fresh.arrays_mut().into_iter().zip(out.arrays_mut());
        for (a, (f, o)) in arrays.enumerate() {
            assert_eq!(f.len(), o.len(), "scene {seed}, array {a}");
            let w = f.len() / n;
            for i in 0..n {
                let (fr, or) = (&f[i * w..][..w], &o[i * w..][..w]);
                if on_screen.binary_search(&(i as u32)).is_ok() {
                    assert_eq!(fr, or, "scene {seed}, array {a}, row {i}");
                } else {
                    assert!(
                        fr.iter().all(|v| *v == 0.0),
                        "scene {seed}: off-screen row {i}"
                    );
                }
            }
        }
        assert_eq!(fresh.pose, out.pose, "scene {seed}");
        if seed >= 6 {
            visible.push(out.rows.clone());
        }
    }
    assert!(
        visible[1].iter().any(|r| !visible[2].contains(r)),
        "the shifted views should see different Gaussians"
    );
}
