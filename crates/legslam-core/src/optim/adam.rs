//! Adam (PyTorch's update, 3DGS settings) over the Gaussians' parameter groups.
//!
//! One global step count for every row, as in 3DGS. Rows come and go with the map:
//! [`Adam::append`] adds rows with zero moments, [`Adam::retain`] drops rows, and
//! [`Adam::gather`] rebuilds the rows from old row indices, copying their moments (for clones
//! and splits; to start a new row from zero moments instead, `append` it).

use rayon::prelude::*;

use super::groups::{Groups, NAMES};
use crate::prefetch::prefetch;
use crate::rows::{gather_rows, retain_rows};
use crate::Real;

/// Rows per parallel task: big enough to amortise scheduling, small enough to balance.
const ROWS_PER_TASK: usize = 1024;

/// The gradient of values that have none, a piece at a time.
static ZEROS: [Real; 4096] = [0.0; 4096];

/// Consecutive rows of one group: parameters, moments and gradients.
struct Chunk<'a> {
    p: &'a mut [Real],
    m: &'a mut [Real],
    v: &'a mut [Real],
    g: &'a [Real],
}

/// The rows of a [`Chunk`] of `width`-value rows that can have a non-zero gradient: `rows`
/// (sorted), numbered from `first`.
#[derive(Clone, Copy)]
struct Listed<'a> {
    width: usize,
    rows: &'a [u32],
    first: usize,
}

/// One group's constants for one step.
#[derive(Clone, Copy, Debug)]
struct Step {
    beta1: Real,
    beta2: Real,
    eps: Real,
    /// The learning rate over the first moment's bias correction.
    step_size: Real,
    /// 1 / sqrt(the second moment's bias correction).
    inv_bias2_sqrt: Real,
}

impl Step {
    /// The update of consecutive values: `m` and `v` follow the gradient `g`, `p` moves.
    #[inline(always)]
    fn update(&self, p: &mut [Real], m: &mut [Real], v: &mut [Real], g: &[Real]) {
        for (((p, m), v), &g) in p.iter_mut().zip(m).zip(v).zip(g) {
            *m = self.beta1 * *m + (1.0 - self.beta1) * g;
            *v = self.beta2 * *v + (1.0 - self.beta2) * g * g;
            *p -= self.step_size * *m / (v.sqrt() * self.inv_bias2_sqrt + self.eps);
        }
    }

    /// [`Step::update`] over the values of `c`, with AVX2 where `avx2` says the CPU has it:
    /// eight values at a time instead of four, through the square root and the division. The
    /// same IEEE operations on each value (no fused multiply-add), so the same bits. With
    /// `listed`, only those rows can have a non-zero gradient: runs of listed rows read theirs,
    /// the runs between them update with zeros instead of reading gradients that are zero (or
    /// stale).
    fn update_fast(&self, avx2: bool, listed: Option<Listed>, c: Chunk) {
        #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
        if avx2 {
            // SAFETY: the caller checked that the CPU has AVX2.
            return unsafe { self.update_avx2(listed, c) };
        }
        let _ = avx2;
        self.update_chunk(listed, c)
    }

    /// [`Step::update_fast`] compiled with AVX2: one call for a whole chunk, all its runs
    /// included (a view's rows come in runs of ~8, too short to pay a call each).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
    #[target_feature(enable = "avx2")]
    unsafe fn update_avx2(&self, listed: Option<Listed>, c: Chunk) {
        self.update_chunk(listed, c)
    }

    /// The body of [`Step::update_fast`], inlined into the portable and the AVX2 entry.
    #[inline(always)]
    fn update_chunk(&self, listed: Option<Listed>, c: Chunk) {
        let Chunk { p, m, v, g } = c;
        let Some(Listed {
            width: w,
            rows: listed,
            first,
        }) = listed
        else {
            // Every value of the chunk in one run, whatever the row width.
            return self.update(p, m, v, g);
        };
        let n = g.len() / w;
        // Values [a, b) with gradients `g` (values update independently of each other).
        let mut run = |a: usize, b: usize, g: &[Real]| {
            self.update(&mut p[a..b], &mut m[a..b], &mut v[a..b], g);
        };
        let (mut at, mut next) = (0, 0);
        while at < n {
            let listed_at = listed.get(next).map_or(n, |&r| r as usize - first);
            let end = if listed_at > at {
                for a in (at * w..listed_at * w).step_by(ZEROS.len()) {
                    let b = (a + ZEROS.len()).min(listed_at * w);
                    run(a, b, &ZEROS[..b - a]);
                }
                listed_at
            } else {
                let mut end = at + 1;
                next += 1;
                while listed.get(next).is_some_and(|&r| r as usize - first == end) {
                    end += 1;
                    next += 1;
                }
                run(at * w, end * w, &g[at * w..end * w]);
                end
            };
            at = end;
        }
    }
}

/// Log-linear decay of a learning rate from its initial value to `final_factor` times it over
/// `steps` steps, then constant (the 3DGS position schedule, `get_expon_lr_func`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExpDecay {
    pub final_factor: Real,
    pub steps: u64,
}

impl ExpDecay {
    fn factor(&self, step: u64) -> Real {
        let progress = (step as f64 / self.steps as f64).min(1.0);
        f64::from(self.final_factor).powf(progress) as Real
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamConfig {
    /// Learning rates per group; `means` is per unit of scene extent.
    pub lr: Groups<Real>,
    /// Scene size the position learning rate scales with.
    pub scene_extent: Real,
    /// Optional decay of the position learning rate.
    pub means_decay: Option<ExpDecay>,
    pub beta1: Real,
    pub beta2: Real,
    pub eps: Real,
    /// "Sparse Adam": a row whose gradient is exactly zero (a Gaussian nothing saw) keeps its
    /// moments and parameters instead of coasting on its momentum.
    pub sparse: bool,
    /// Sparse Adam for the features group alone, the others dense: a Gaussian that reached no
    /// feature pixel keeps its feature and its moments. A feature enters no colour or depth
    /// render, and a coarse feature layer reaches under half the map in a step (the mapper
    /// bench's): dense updates there are memory traffic that coasts features on momentum.
    pub sparse_features: bool,
    /// Sparse Adam for the colour (SH) group too: a Gaussian that made no pixel's colour keeps
    /// its SH coefficients and moments. With SH degree 3 they are 48 of a row's 59 dense values,
    /// and a view leaves much of a map off screen or hidden.
    pub sparse_sh: bool,
}

impl Default for AdamConfig {
    /// The LEG-SLAM / 3DGS settings (paper-notes.md), scene extent 1, no decay, dense updates.
    fn default() -> Self {
        AdamConfig {
            lr: Groups {
                means: 3.2e-4,
                log_scales: 5e-3,
                quats: 1e-3,
                opacity_logits: 0.05,
                sh: 2.5e-3,
                features: 1.5e-3,
            },
            scene_extent: 1.0,
            means_decay: None,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
            sparse: false,
            sparse_features: false,
            sparse_sh: false,
        }
    }
}

impl AdamConfig {
    /// Which groups take the sparse step (`sparse`, or their own option).
    pub(crate) fn sparse_groups(&self) -> Groups<bool> {
        Groups {
            sh: self.sparse || self.sparse_sh,
            features: self.sparse || self.sparse_features,
            ..Groups::splat(self.sparse)
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        for (name, lr) in NAMES.iter().zip(self.lr.into_array()) {
            if !(lr.is_finite() && lr >= 0.0) {
                return Err(format!(
                    "the {name} learning rate must be finite and >= 0, got {lr}"
                ));
            }
        }
        if !(self.scene_extent.is_finite() && self.scene_extent > 0.0) {
            return Err(format!(
                "the scene extent must be > 0, got {}",
                self.scene_extent
            ));
        }
        if let Some(d) = self.means_decay {
            if !(d.final_factor.is_finite() && d.final_factor > 0.0) || d.steps == 0 {
                return Err(format!(
                    "the position decay needs final_factor > 0 and steps > 0, got {d:?}"
                ));
            }
        }
        for (name, b) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&b) {
                return Err(format!("{name} must lie in [0, 1), got {b}"));
            }
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return Err(format!("eps must be > 0, got {}", self.eps));
        }
        Ok(())
    }
}

/// Adam state for N Gaussians: first and second moments laid out like the parameters.
#[derive(Clone, Debug)]
pub struct Adam {
    pub config: AdamConfig,
    widths: [usize; 6],
    m: [Vec<Real>; 6],
    v: [Vec<Real>; 6],
    len: usize,
    steps: u64,
}

impl Adam {
    /// State for `len` Gaussians with `sh_coeffs` SH coefficients per channel and
    /// `num_features` feature channels, all moments zero.
    pub fn new(
        config: AdamConfig,
        len: usize,
        sh_coeffs: usize,
        num_features: usize,
    ) -> Result<Self, String> {
        config.validate()?;
        let widths = [3, 3, 4, 1, 3 * sh_coeffs, num_features];
        Ok(Adam {
            config,
            widths,
            m: widths.map(|w| vec![0.0; len * w]),
            v: widths.map(|w| vec![0.0; len * w]),
            len,
            steps: 0,
        })
    }

    /// Number of Gaussians (rows).
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// Values per row of each group.
    pub fn widths(&self) -> Groups<usize> {
        Groups::from_array(self.widths)
    }

    /// First and second moments, laid out like the parameters.
    pub fn moments(&self) -> (Groups<&[Real]>, Groups<&[Real]>) {
        (
            Groups::from_array(self.m.each_ref().map(|a| &a[..])),
            Groups::from_array(self.v.each_ref().map(|a| &a[..])),
        )
    }

    /// The learning rates the next step will use (position scaled by the extent and decayed).
    pub fn learning_rates(&self) -> Groups<Real> {
        let c = &self.config;
        let decay = c.means_decay.map_or(1.0, |d| d.factor(self.steps));
        Groups {
            means: c.lr.means * c.scene_extent * decay,
            ..c.lr
        }
    }

    /// One Adam step on every group: `params -= lr m_hat / (sqrt(v_hat) + eps)`.
    pub fn step(
        &mut self,
        params: Groups<&mut [Real]>,
        grads: Groups<&[Real]>,
    ) -> Result<(), String> {
        self.step_rows(params, grads, None)
    }

    /// [`Adam::step`], told that only the sorted rows `rows` can have a non-zero gradient (a
    /// render's visible Gaussians): sparse Adam then visits only those, dense Adam every row,
    /// with zeros for the others' gradients (which it does not read: a reused buffer's
    /// off-screen rows may be stale, see `Gradients::rows`).
    pub fn step_rows(
        &mut self,
        params: Groups<&mut [Real]>,
        grads: Groups<&[Real]>,
        rows: Option<&[u32]>,
    ) -> Result<(), String> {
        self.config.validate()?;
        let params = params.into_array();
        let grads = grads.into_array();
        for i in 0..6 {
            let want = self.len * self.widths[i];
            if params[i].len() != want || grads[i].len() != want {
                return Err(format!(
                    "Adam holds {} Gaussians: {} parameters and gradients must hold {want} values, got {} and {}",
                    self.len, NAMES[i], params[i].len(), grads[i].len()
                ));
            }
        }
        if let Some(&bad) = rows.and_then(|r| r.iter().find(|&&r| r as usize >= self.len)) {
            return Err(format!(
                "row {bad} is out of range for {} Gaussians",
                self.len
            ));
        }
        let lrs = self.learning_rates().into_array();
        let sparse_groups = self.config.sparse_groups().into_array();
        self.steps += 1;
        let c = self.config;
        let t = self.steps as f64;
        let bias1 = 1.0 - f64::from(c.beta1).powf(t);
        let bias2_sqrt = (1.0 - f64::from(c.beta2).powf(t)).sqrt();
        let avx2 = crate::raster::avx2_available();
        for (i, (p, g)) in params.into_iter().zip(grads).enumerate() {
            let (w, sparse) = (self.widths[i], sparse_groups[i]);
            if w == 0 {
                continue;
            }
            let k = Step {
                beta1: c.beta1,
                beta2: c.beta2,
                eps: c.eps,
                step_size: (f64::from(lrs[i]) / bias1) as Real,
                inv_bias2_sqrt: (1.0 / bias2_sqrt) as Real,
            };
            let chunk = ROWS_PER_TASK * w;
            p.par_chunks_mut(chunk)
                .zip(self.m[i].par_chunks_mut(chunk))
                .zip(self.v[i].par_chunks_mut(chunk))
                .zip(g.par_chunks(chunk))
                .enumerate()
                .for_each(|(ci, (((p, m), v), g))| {
                    let first = ci * ROWS_PER_TASK;
                    if !sparse {
                        let listed = rows.map(|rows| Listed {
                            width: w,
                            rows: rows_in(rows, first, g.len() / w),
                            first,
                        });
                        return k.update_fast(avx2, listed, Chunk { p, m, v, g });
                    }
                    // Row by row, skipping those whose gradient is exactly zero.
                    let update = |r: usize, p: &mut [Real], m: &mut [Real], v: &mut [Real]| {
                        let row = r * w..(r + 1) * w;
                        let g = &g[row.clone()];
                        if g.iter().any(|&x| x != 0.0) {
                            k.update(&mut p[row.clone()], &mut m[row.clone()], &mut v[row], g);
                        }
                    };
                    match rows {
                        Some(rows) => {
                            let mine = rows_in(rows, first, g.len() / w);
                            for (at, &r) in mine.iter().enumerate() {
                                if let Some(&ahead) = mine.get(at + ROW_PREFETCH) {
                                    let o = (ahead as usize - first) * w;
                                    prefetch(&p[o..o + w]);
                                    prefetch(&m[o..o + w]);
                                    prefetch(&v[o..o + w]);
                                    prefetch(&g[o..o + w]);
                                }
                                update(r as usize - first, p, m, v)
                            }
                        }
                        None => (0..g.len() / w).for_each(|r| update(r, p, m, v)),
                    }
                });
        }
        Ok(())
    }

    /// Adds `n` rows at the end with zero moments (new Gaussians).
    pub fn append(&mut self, n: usize) {
        self.len += n;
        for i in 0..6 {
            let want = self.len * self.widths[i];
            self.m[i].resize(want, 0.0);
            self.v[i].resize(want, 0.0);
        }
    }

    /// Keeps the rows where `keep` is true, in order (pruning).
    pub fn retain(&mut self, keep: &[bool]) -> Result<(), String> {
        if keep.len() != self.len {
            return Err(format!(
                "retain needs one flag per Gaussian ({}), got {}",
                self.len,
                keep.len()
            ));
        }
        for i in 0..6 {
            for a in [&mut self.m[i], &mut self.v[i]] {
                retain_rows(a, self.widths[i], keep);
            }
        }
        self.len = keep.iter().filter(|&&k| k).count();
        Ok(())
    }

    /// Replaces the rows by old rows `indices[0], indices[1], ...` with their moments
    /// (repeats allowed: a clone or split child inherits its parent's moments).
    pub fn gather(&mut self, indices: &[usize]) -> Result<(), String> {
        if let Some(&bad) = indices.iter().find(|&&r| r >= self.len) {
            return Err(format!(
                "gather index {bad} is out of range for {} Gaussians",
                self.len
            ));
        }
        let widest = self.widths.iter().max().copied().unwrap_or(0);
        let mut spare = Vec::with_capacity(indices.len() * widest);
        for i in 0..6 {
            for a in [&mut self.m[i], &mut self.v[i]] {
                gather_rows(a, self.widths[i], indices, &mut spare);
            }
        }
        self.len = indices.len();
        Ok(())
    }
}

/// Rescales each (w, x, y, z) quaternion to unit length, as needed after every step; a zero or
/// non-finite one becomes the identity (1, 0, 0, 0). With `rows` (sorted), only those.
pub fn normalize_quats(quats: &mut [Real], rows: Option<&[u32]>) -> Result<(), String> {
    if quats.len() % 4 != 0 {
        return Err(format!(
            "quats must hold 4 values per Gaussian, got {} values",
            quats.len()
        ));
    }
    let normalize = |q: &mut [Real]| {
        let norm = q.iter().map(|v| v * v).sum::<Real>().sqrt();
        if norm > 0.0 && norm.is_finite() {
            q.iter_mut().for_each(|v| *v /= norm);
        } else {
            q.copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
        }
    };
    quats
        .par_chunks_mut(4 * ROWS_PER_TASK)
        .enumerate()
        .for_each(|(ci, c)| match rows {
            Some(rows) => {
                let first = ci * ROWS_PER_TASK;
                for &r in rows_in(rows, first, c.len() / 4) {
                    normalize(&mut c[(r as usize - first) * 4..][..4]);
                }
            }
            None => c.chunks_exact_mut(4).for_each(normalize),
        });
    Ok(())
}

/// How many of a task's listed rows ahead sparse Adam prefetches (the rows lie in runs, with
/// jumps the hardware prefetcher misses: its loads stalled; 2 and 8 were slower than 4).
const ROW_PREFETCH: usize = 4;

/// The entries of the sorted list `rows` in [first, first + len).
pub(crate) fn rows_in(rows: &[u32], first: usize, len: usize) -> &[u32] {
    let at = |x: usize| rows.partition_point(|&r| (r as usize) < x);
    &rows[at(first)..at(first + len)]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// A step with 3DGS's betas, some way into training.
    fn some_step() -> Step {
        Step {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
            step_size: 2.5e-3 / 0.19,
            inv_bias2_sqrt: 1.0 / (0.002 as Real).sqrt(),
        }
    }

    fn bits(x: &[Real]) -> Vec<u64> {
        x.iter().map(|v| u64::from(v.to_bits())).collect()
    }

    /// The AVX2 update against the plain one, bit for bit, on random moments and gradients
    /// (zeros among them) of lengths that leave every tail (where the CPU has AVX2).
    #[test]
    fn the_avx2_update_gives_the_plain_bits() {
        if !crate::raster::avx2_available() {
            eprintln!("no AVX2 here: only the plain update runs");
            return;
        }
        let mut rng = Rng::new(5);
        for len in [1, 3, 7, 8, 9, 31, 64, 1000] {
            let mut draw = |scale: f64| -> Vec<Real> {
                (0..len)
                    .map(|i| {
                        if i % 5 == 0 {
                            0.0
                        } else {
                            (rng.normal() * scale) as Real
                        }
                    })
                    .collect()
            };
            let (p, m, g) = (draw(1.0), draw(1e-2), draw(1e-3));
            let v: Vec<Real> = draw(1e-3).iter().map(|x| x * x).collect();
            let k = some_step();
            let (mut pa, mut ma, mut va) = (p.clone(), m.clone(), v.clone());
            let (mut pb, mut mb, mut vb) = (p.clone(), m, v);
            k.update(&mut pa, &mut ma, &mut va, &g);
            let c = Chunk {
                p: &mut pb,
                m: &mut mb,
                v: &mut vb,
                g: &g,
            };
            k.update_fast(true, None, c);
            assert_eq!(bits(&pa), bits(&pb), "parameters, {len} values");
            assert_eq!(bits(&ma), bits(&mb), "first moments, {len} values");
            assert_eq!(bits(&va), bits(&vb), "second moments, {len} values");
            if len > 1 {
                assert_ne!(bits(&pa), bits(&p), "the update must move the parameters");
            }
        }
    }

    /// Both paths of the listed update against the plain update of every row with the
    /// unlisted rows' gradients zeroed, bit for bit: those rows' gradients (garbage here) are
    /// never read, runs and gaps of every length, rows wider than the zeros' piece.
    #[test]
    fn listed_rows_give_the_bits_of_zero_gradients_elsewhere() {
        let mut rng = Rng::new(6);
        let k = some_step();
        for w in [1, 3, 48, 5000] {
            let n = 40;
            let mut draw =
                |len: usize| -> Vec<Real> { (0..len).map(|_| rng.normal() as Real).collect() };
            let (p, m, g) = (draw(n * w), draw(n * w), draw(n * w));
            let v: Vec<Real> = draw(n * w).iter().map(|x| x * x).collect();
            // Runs of 1, 2, 3 ... rows with gaps of 1, 2, 3 ..., from row 1 (first = 100).
            let mut listed = Vec::new();
            let (mut r, mut len) = (1, 1);
            while r < n {
                listed.extend((r..(r + len).min(n)).map(|i| (100 + i) as u32));
                r += 2 * len;
                len += 1;
            }
            let mut zeroed = g.clone();
            for i in 0..n {
                if !listed.contains(&((100 + i) as u32)) {
                    zeroed[i * w..(i + 1) * w].fill(0.0);
                }
            }
            let (mut pa, mut ma, mut va) = (p.clone(), m.clone(), v.clone());
            k.update(&mut pa, &mut ma, &mut va, &zeroed);
            let paths = if crate::raster::avx2_available() {
                vec![false, true]
            } else {
                vec![false]
            };
            for avx2 in paths {
                let (mut pb, mut mb, mut vb) = (p.clone(), m.clone(), v.clone());
                let rows = Listed {
                    width: w,
                    rows: &listed,
                    first: 100,
                };
                let c = Chunk {
                    p: &mut pb,
                    m: &mut mb,
                    v: &mut vb,
                    g: &g,
                };
                k.update_fast(avx2, Some(rows), c);
                assert_eq!(bits(&pa), bits(&pb), "parameters, width {w}, avx2 {avx2}");
                assert_eq!(
                    bits(&ma),
                    bits(&mb),
                    "first moments, width {w}, avx2 {avx2}"
                );
                assert_eq!(
                    bits(&va),
                    bits(&vb),
                    "second moments, width {w}, avx2 {avx2}"
                );
            }
        }
    }
}
