//! Adam against a plain per-row f64 reference through steps, appends, prunes and gathers;
//! convergence on a quadratic; moments following their rows.

mod common;

use common::Rng;
use legslam_core::optim::{normalize_quats, Adam, AdamConfig, ExpDecay, Groups};
use legslam_core::Real;

type Rows = Vec<Vec<f64>>;

/// Textbook Adam (PyTorch form) on rows of f64, one group at a time.
struct Reference {
    cfg: AdamConfig,
    m: [Rows; 6],
    v: [Rows; 6],
    t: u64,
}

impl Reference {
    fn lr(&self, group: usize) -> f64 {
        let c = &self.cfg;
        let base = c.lr.into_array()[group] as f64;
        if group != 0 {
            return base;
        }
        let decay = c.means_decay.map_or(1.0, |d| {
            (d.final_factor as f64).powf((self.t as f64 / d.steps as f64).min(1.0))
        });
        base * c.scene_extent as f64 * decay
    }

    fn step(&mut self, p: &mut [Rows; 6], g: &[Rows; 6]) {
        let lrs: Vec<f64> = (0..6).map(|i| self.lr(i)).collect();
        self.t += 1;
        let (b1, b2, eps) = (
            self.cfg.beta1 as f64,
            self.cfg.beta2 as f64,
            self.cfg.eps as f64,
        );
        let t = self.t as i32;
        for i in 0..6 {
            for r in 0..p[i].len() {
                let sparse = self.cfg.sparse
                    || self.cfg.sparse_features && i == 5
                    || self.cfg.sparse_sh && i == 4;
                if sparse && g[i][r].iter().all(|&x| x == 0.0) {
                    continue;
                }
                for j in 0..p[i][r].len() {
                    let gr = g[i][r][j];
                    let m = &mut self.m[i][r][j];
                    *m = b1 * *m + (1.0 - b1) * gr;
                    let v = &mut self.v[i][r][j];
                    *v = b2 * *v + (1.0 - b2) * gr * gr;
                    let m_hat = *m / (1.0 - b1.powi(t));
                    let v_hat = *v / (1.0 - b2.powi(t));
                    p[i][r][j] -= lrs[i] * m_hat / (v_hat.sqrt() + eps);
                }
            }
        }
    }
}

fn borrow(p: &mut [Vec<Real>; 6]) -> Groups<&mut [Real]> {
    Groups::from_array(p.each_mut().map(|v| &mut v[..]))
}

fn view(g: &[Vec<Real>; 6]) -> Groups<&[Real]> {
    Groups::from_array(g.each_ref().map(|v| &v[..]))
}

const WIDTHS: [usize; 6] = [3, 3, 4, 1, 12, 5];

fn random_rows(rng: &mut Rng, n: usize, w: usize) -> Rows {
    (0..n)
        .map(|_| (0..w).map(|_| rng.normal()).collect())
        .collect()
}

fn flat(rows: &Rows) -> Vec<Real> {
    rows.iter().flatten().map(|&x| x as Real).collect()
}

/// Random gradients; with `zero_rows`, about a third of the rows are exactly zero, the
/// features of about a third of the others (a Gaussian on screen that reached no feature pixel)
/// and the SH of about a third (one hidden behind others in the colour layer).
fn grads(rng: &mut Rng, n: usize, zero_rows: bool) -> [Rows; 6] {
    let dead: Vec<bool> = (0..n).map(|_| zero_rows && rng.next_f64() < 0.3).collect();
    let featureless: Vec<bool> = (0..n).map(|_| zero_rows && rng.next_f64() < 0.3).collect();
    let colourless: Vec<bool> = (0..n).map(|_| zero_rows && rng.next_f64() < 0.3).collect();
    let mut groups = WIDTHS.map(|w| random_rows(rng, n, w));
    for (i, g) in groups.iter_mut().enumerate() {
        for (r, row) in g.iter_mut().enumerate() {
            if dead[r] || i == 5 && featureless[r] || i == 4 && colourless[r] {
                row.iter_mut().for_each(|x| *x = 0.0);
            }
        }
    }
    groups
}

#[cfg(feature = "f64")]
const TOL: f64 = 1e-12;
// f32: each step moves a value by about lr with ~1e-7 relative rounding in the update and in
// the stored parameter; after ten steps 1e-5 is comfortably above that.
#[cfg(not(feature = "f64"))]
const TOL: f64 = 1e-5;

/// Starts from `n` rows; beyond 1024 rows the update runs as several parallel tasks. With
/// `sparse`, `sparse_features` or `sparse_sh`, some rows' gradients (or features' or SH's alone)
/// are zero.
fn run_scenario(sparse: bool, sparse_features: bool, sparse_sh: bool, n: usize) {
    let mut rng = Rng::new(
        20 + u64::from(sparse) + 2 * u64::from(sparse_features) + 4 * u64::from(sparse_sh),
    );
    let cfg = AdamConfig {
        lr: Groups {
            means: 2e-2,
            log_scales: 3e-2,
            quats: 1e-2,
            opacity_logits: 5e-2,
            sh: 4e-2,
            features: 6e-2,
        },
        scene_extent: 2.5,
        means_decay: Some(ExpDecay {
            final_factor: 0.01,
            steps: 6,
        }),
        sparse,
        sparse_features,
        sparse_sh,
        ..AdamConfig::default()
    };
    let zero_rows = sparse || sparse_features || sparse_sh;
    let mut n = n;
    let mut adam = Adam::new(cfg, n, 4, 5).unwrap();
    let mut reference = Reference {
        cfg,
        m: WIDTHS.map(|w| vec![vec![0.0; w]; n]),
        v: WIDTHS.map(|w| vec![vec![0.0; w]; n]),
        t: 0,
    };
    let mut params: [Rows; 6] = WIDTHS.map(|w| random_rows(&mut rng, n, w));
    // The engine's parameters start as the f32 rounding of the reference's.
    params
        .iter_mut()
        .flatten()
        .flatten()
        .for_each(|x| *x = *x as Real as f64);
    let mut engine: [Vec<Real>; 6] = params.each_ref().map(flat);

    let step = |rng: &mut Rng,
                adam: &mut Adam,
                reference: &mut Reference,
                params: &mut [Rows; 6],
                engine: &mut [Vec<Real>; 6],
                n: usize| {
        let g = grads(rng, n, zero_rows);
        let g_flat: [Vec<Real>; 6] = g.each_ref().map(flat);
        // Both sides see the same (f32-rounded) gradient.
        let g: [Rows; 6] = g.map(|rows| {
            rows.into_iter()
                .map(|r| r.into_iter().map(|x| x as Real as f64).collect())
                .collect()
        });
        // Told which rows can have a gradient (and some that have none): sparse Adam visits
        // only those, dense Adam every row all the same.
        let rows: Vec<u32> = (0..n)
            .filter(|&r| r % 5 == 0 || g.iter().any(|grp| grp[r].iter().any(|&x| x != 0.0)))
            .map(|r| r as u32)
            .collect();
        adam.step_rows(borrow(engine), view(&g_flat), Some(&rows))
            .unwrap();
        reference.step(params, &g);
        for i in 0..6 {
            let want = flat(&params[i]);
            for (j, (a, b)) in engine[i].iter().zip(&want).enumerate() {
                assert!(
                    ((a - b) as f64).abs() < TOL,
                    "group {i} value {j} after step {}: {a} vs reference {b}",
                    reference.t
                );
            }
        }
    };

    for _ in 0..3 {
        step(
            &mut rng,
            &mut adam,
            &mut reference,
            &mut params,
            &mut engine,
            n,
        );
    }
    // Seven new Gaussians with zero moments.
    adam.append(7);
    for i in 0..6 {
        let new = random_rows(&mut rng, 7, WIDTHS[i]);
        let new: Rows = new
            .into_iter()
            .map(|r| r.into_iter().map(|x| x as Real as f64).collect())
            .collect();
        engine[i].extend(flat(&new));
        params[i].extend(new);
        reference.m[i].extend(vec![vec![0.0; WIDTHS[i]]; 7]);
        reference.v[i].extend(vec![vec![0.0; WIDTHS[i]]; 7]);
    }
    n += 7;
    for _ in 0..2 {
        step(
            &mut rng,
            &mut adam,
            &mut reference,
            &mut params,
            &mut engine,
            n,
        );
    }
    // Prune about a quarter.
    let keep: Vec<bool> = (0..n).map(|_| rng.next_f64() > 0.25).collect();
    adam.retain(&keep).unwrap();
    let keep_rows = |rows: &mut Rows| {
        let mut it = keep.iter();
        rows.retain(|_| *it.next().unwrap());
    };
    for i in 0..6 {
        keep_rows(&mut params[i]);
        keep_rows(&mut reference.m[i]);
        keep_rows(&mut reference.v[i]);
        engine[i] = flat(&params[i]);
    }
    n = adam.len();
    assert_eq!(n, params[0].len());
    for _ in 0..2 {
        step(
            &mut rng,
            &mut adam,
            &mut reference,
            &mut params,
            &mut engine,
            n,
        );
    }
    // Clone some, split others (children inherit moments), drop the rest.
    let indices: Vec<usize> = (0..n + 10)
        .map(|_| (rng.next_f64() * n as f64) as usize)
        .collect();
    adam.gather(&indices).unwrap();
    let pick = |rows: &Rows| -> Rows { indices.iter().map(|&r| rows[r].clone()).collect() };
    for i in 0..6 {
        params[i] = pick(&params[i]);
        reference.m[i] = pick(&reference.m[i]);
        reference.v[i] = pick(&reference.v[i]);
        engine[i] = flat(&params[i]);
    }
    n = indices.len();
    for _ in 0..3 {
        step(
            &mut rng,
            &mut adam,
            &mut reference,
            &mut params,
            &mut engine,
            n,
        );
    }
    let (m, v) = adam.moments();
    for (i, (m, v)) in m.into_array().iter().zip(v.into_array()).enumerate() {
        for (a, b) in m.iter().zip(reference.m[i].iter().flatten()) {
            assert!(((*a as f64) - b).abs() < TOL, "first moment of group {i}");
        }
        for (a, b) in v.iter().zip(reference.v[i].iter().flatten()) {
            assert!(((*a as f64) - b).abs() < TOL, "second moment of group {i}");
        }
    }
}

#[test]
fn matches_reference_through_appends_prunes_and_gathers() {
    run_scenario(false, false, false, 50);
    run_scenario(false, false, false, 2500);
}

/// Dense Adam told which rows can have a gradient ignores the others' values (a reused
/// gradient buffer leaves them stale) and gives the bits of a step whose other rows are zero:
/// runs and gaps of every length, across parallel tasks, a wide group crossing the pieces of
/// zeros it is fed in.
#[test]
fn dense_listed_rows_equal_zeros_elsewhere() {
    let n = 2500;
    let widths = [3, 3, 4, 1, 48, 100];
    let mut rng = Rng::new(23);
    let mut a = Adam::new(AdamConfig::default(), n, 16, 100).unwrap();
    let mut b = a.clone();
    let init: [Vec<Real>; 6] = widths.map(|w| (0..n * w).map(|_| rng.normal() as Real).collect());
    let (mut pa, mut pb) = (init.clone(), init);
    for step in 0..4 {
        // Runs of listed rows of random lengths, with gaps of random lengths (some long).
        let mut listed = Vec::new();
        let mut r = 0;
        while r < n {
            let run = 1 + rng.below(if step % 2 == 0 { 5 } else { 300 });
            listed.extend((r..(r + run).min(n)).map(|i| i as u32));
            r += run + rng.below(if step < 2 { 4 } else { 2000 });
        }
        let garbage: [Vec<Real>; 6] =
            widths.map(|w| (0..n * w).map(|_| rng.normal() as Real).collect());
        let mut zeroed = garbage.clone();
        for (z, w) in zeroed.iter_mut().zip(widths) {
            for i in 0..n {
                if listed.binary_search(&(i as u32)).is_err() {
                    z[i * w..(i + 1) * w].fill(0.0);
                }
            }
        }
        a.step_rows(borrow(&mut pa), view(&garbage), Some(&listed))
            .unwrap();
        b.step(borrow(&mut pb), view(&zeroed)).unwrap();
        assert_eq!(pa, pb, "step {step}");
    }
    assert_eq!(a.moments(), b.moments());
}

/// Features alone sparse: a row without a feature gradient keeps its feature and moments,
/// while every group else (zero rows included) takes the dense update.
#[test]
fn sparse_features_match_reference_the_other_groups_dense() {
    run_scenario(false, true, false, 50);
    run_scenario(false, true, false, 2500);
}

/// SH and features sparse (SLAM's default), the geometry dense: a row without a colour or
/// feature gradient keeps those values and moments while its geometry takes the dense update.
#[test]
fn sparse_sh_and_features_match_reference_the_geometry_dense() {
    run_scenario(false, true, true, 50);
    run_scenario(false, true, true, 2500);
}

#[test]
fn sparse_matches_reference_and_leaves_zero_rows_alone() {
    run_scenario(true, false, false, 50);
    let cfg = AdamConfig {
        sparse: true,
        ..AdamConfig::default()
    };
    let mut adam = Adam::new(cfg, 2, 1, 0).unwrap();
    let mut p = [
        vec![1.0; 6],
        vec![0.0; 6],
        vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        vec![0.5; 2],
        vec![0.2; 6],
        vec![],
    ];
    let g1 = [
        vec![1.0; 6],
        vec![1.0; 6],
        vec![1.0; 8],
        vec![1.0; 2],
        vec![1.0; 6],
        vec![],
    ];
    let mut g2 = g1.clone();
    g2.iter_mut().for_each(|g| {
        let half = g.len() / 2;
        g[half..].iter_mut().for_each(|x| *x = 0.0)
    });
    adam.step(borrow(&mut p), view(&g1)).unwrap();
    let (before, (m_before, _)) = (p.clone(), {
        let (m, v) = adam.moments();
        (m.map(|s| s.to_vec()), v.map(|s| s.to_vec()))
    });
    adam.step(borrow(&mut p), view(&g2)).unwrap();
    let (m_after, _) = adam.moments();
    let m_before = m_before.into_array();
    for (i, (m_after, m_before)) in m_after.into_array().iter().zip(&m_before).enumerate() {
        let half = p[i].len() / 2;
        assert_eq!(
            p[i][half..],
            before[i][half..],
            "group {i}: the unseen row moved"
        );
        assert_eq!(
            m_after[half..],
            m_before[half..],
            "group {i}: the unseen row's moments changed"
        );
        assert!(
            p[i][..half] != before[i][..half] || half == 0,
            "group {i}: the seen row stood still"
        );
    }
}

#[test]
fn minimises_a_quadratic() {
    let mut rng = Rng::new(22);
    let n = 40;
    let cfg = AdamConfig {
        lr: Groups::from_array([0.01; 6]),
        ..AdamConfig::default()
    };
    let mut adam = Adam::new(cfg, n, 1, 8).unwrap();
    let widths = adam.widths().into_array();
    let target: Vec<Vec<Real>> = widths
        .iter()
        .map(|&w| (0..n * w).map(|_| rng.normal() as Real).collect())
        .collect();
    let mut p: [Vec<Real>; 6] = widths.map(|w| vec![0.0; n * w]);
    let mut g: [Vec<Real>; 6] = widths.map(|w| vec![0.0; n * w]);
    for _ in 0..3000 {
        for i in 0..6 {
            for ((g, p), t) in g[i].iter_mut().zip(&p[i]).zip(&target[i]) {
                *g = p - t;
            }
        }
        adam.step(borrow(&mut p), view(&g)).unwrap();
    }
    for i in 0..6 {
        let worst = p[i]
            .iter()
            .zip(&target[i])
            .fold(0.0 as Real, |m, (a, b)| m.max((a - b).abs()));
        assert!(worst < 1e-3, "group {i}: {worst} from the minimum");
    }
}

#[test]
fn moments_follow_their_rows() {
    let mut adam = Adam::new(AdamConfig::default(), 4, 1, 2).unwrap();
    let widths = adam.widths().into_array();
    let mut p: [Vec<Real>; 6] = widths.map(|w| vec![0.0; 4 * w]);
    // Row r's gradient is r + 1 everywhere, so its first moment is 0.1 (r + 1).
    let g: [Vec<Real>; 6] = widths.map(|w| (0..4 * w).map(|i| (i / w + 1) as Real).collect());
    adam.step(borrow(&mut p), view(&g)).unwrap();
    let rows_of = |adam: &Adam| -> Vec<Vec<Real>> {
        let (m, _) = adam.moments();
        m.into_array()
            .iter()
            .zip(widths)
            .map(|(m, w)| m.chunks(w).map(|r| (r[0] * 10.0).round()).collect())
            .collect()
    };
    adam.gather(&[3, 0, 3, 1, 2]).unwrap();
    assert!(rows_of(&adam)
        .iter()
        .all(|r| r == &[4.0, 1.0, 4.0, 2.0, 3.0]));
    adam.retain(&[false, true, true, false, true]).unwrap();
    adam.append(2);
    assert_eq!(adam.len(), 5);
    assert!(rows_of(&adam)
        .iter()
        .all(|r| r == &[1.0, 4.0, 3.0, 0.0, 0.0]));
    let (_, v) = adam.moments();
    assert!(v
        .into_array()
        .iter()
        .zip(widths)
        .all(|(v, w)| v.len() == 5 * w && v[3 * w..].iter().all(|&x| x == 0.0)));
}

#[test]
fn position_rate_scales_with_extent_and_decays() {
    let cfg = AdamConfig {
        scene_extent: 4.0,
        means_decay: Some(ExpDecay {
            final_factor: 0.01,
            steps: 2,
        }),
        ..AdamConfig::default()
    };
    let mut adam = Adam::new(cfg, 0, 1, 0).unwrap();
    let lr0 = adam.learning_rates();
    assert!((lr0.means - 3.2e-4 * 4.0).abs() < 1e-9);
    assert_eq!(
        (lr0.sh, lr0.features, lr0.opacity_logits),
        (2.5e-3, 1.5e-3, 0.05)
    );
    assert_eq!((lr0.log_scales, lr0.quats), (5e-3, 1e-3));
    let (mut p, g): ([Vec<Real>; 6], [Vec<Real>; 6]) = Default::default();
    let mut rates = vec![];
    for _ in 0..3 {
        adam.step(borrow(&mut p), view(&g)).unwrap();
        rates.push(adam.learning_rates().means);
    }
    let want = [3.2e-4 * 4.0 * 0.1, 3.2e-4 * 4.0 * 0.01, 3.2e-4 * 4.0 * 0.01];
    for (a, b) in rates.iter().zip(want) {
        assert!((a - b).abs() < 1e-9, "{a} vs {b}");
    }
}

#[test]
fn quaternions_are_renormalised() {
    let mut q = [2.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0];
    let mut rows_only = q;
    normalize_quats(&mut q, None).unwrap();
    assert_eq!(q[..4], [1.0, 0.0, 0.0, 0.0]);
    assert!(q[4..8].iter().all(|&v| (v - 0.5).abs() < 1e-6));
    assert_eq!(q[8..], [1.0, 0.0, 0.0, 0.0]);
    assert!(normalize_quats(&mut q[..5], None).is_err());
    // Only the rows named: the first stays as it was.
    normalize_quats(&mut rows_only, Some(&[1, 2])).unwrap();
    assert_eq!(rows_only[..4], [2.0, 0.0, 0.0, 0.0]);
    assert_eq!(rows_only[4..], q[4..]);
}

#[test]
fn bad_sizes_and_settings_are_errors() {
    let bad = AdamConfig {
        beta2: 1.0,
        ..AdamConfig::default()
    };
    assert!(Adam::new(bad, 1, 1, 0).unwrap_err().contains("beta2"));
    let mut adam = Adam::new(AdamConfig::default(), 2, 1, 3).unwrap();
    let widths = adam.widths().into_array();
    let mut p: [Vec<Real>; 6] = widths.map(|w| vec![0.0; 2 * w]);
    let mut g: [Vec<Real>; 6] = widths.map(|w| vec![0.0; 2 * w]);
    g[5].pop();
    let err = adam.step(borrow(&mut p), view(&g)).unwrap_err();
    assert!(err.contains("features"), "{err}");
    assert_eq!(adam.steps(), 0);
    assert!(adam.retain(&[true]).is_err());
    assert!(adam.gather(&[0, 2]).unwrap_err().contains("index 2"));
}

/// Sparse Adam (throughout, or for the features alone) on rows whose gradients are all
/// non-zero takes the dense step bit for bit: its row-by-row path, vectorised apart from the
/// dense one, makes the same IEEE operations on every value.
#[test]
fn sparse_rows_with_gradients_take_the_dense_bits() {
    let n = 700;
    let widths = [3, 3, 4, 1, 48, 64];
    for (sparse, sparse_features) in [(true, false), (false, true)] {
        let mut rng = Rng::new(31 + u64::from(sparse));
        let mut dense = Adam::new(AdamConfig::default(), n, 16, 64).unwrap();
        let cfg = AdamConfig {
            sparse,
            sparse_features,
            ..AdamConfig::default()
        };
        let mut sp = Adam::new(cfg, n, 16, 64).unwrap();
        let init: [Vec<Real>; 6] =
            widths.map(|w| (0..n * w).map(|_| rng.normal() as Real).collect());
        let (mut pd, mut ps) = (init.clone(), init);
        let all: Vec<u32> = (0..n as u32).collect();
        for step in 0..4 {
            // Away from zero, so that every row has a gradient.
            let g: [Vec<Real>; 6] =
                widths.map(|w| (0..n * w).map(|_| 0.1 + rng.next_f64() as Real).collect());
            let rows = (step % 2 == 1).then_some(&all[..]);
            dense.step_rows(borrow(&mut pd), view(&g), rows).unwrap();
            sp.step_rows(borrow(&mut ps), view(&g), rows).unwrap();
            assert_eq!(pd, ps, "step {step}, sparse {sparse}");
        }
        assert_eq!(dense.moments(), sp.moments());
    }
}
