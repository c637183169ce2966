//! Block-sparse Cholesky factorisation of the pose graph's normal equations: one 6x6 block row
//! per free node, eliminated in minimum-degree order so that a chain with loop edges fills in
//! little. (A dense 6n x 6n nalgebra Cholesky is O(n^3): seconds at n = 500.)
//!
//! [`Pattern`] is the symbolic part, computed once per set of edges: the elimination order, where
//! every block of the factor `L` lives, and the list of block updates; [`Pattern::factor`] and
//! [`Pattern::solve`] are then plain arithmetic on an array of blocks, once per iteration.

use std::collections::BTreeSet;

use nalgebra::{Matrix6, Vector6};

/// Where the blocks of `H` (lower triangle) and of its factor live, in elimination order.
pub(crate) struct Pattern {
    /// Position in the elimination order of each variable (block row).
    position: Vec<usize>,
    /// Blocks of column `k` (a position) are `start[k]..start[k + 1]`: the diagonal first, then
    /// the rows below it, ascending.
    start: Vec<usize>,
    /// Row position of each block.
    row: Vec<usize>,
    /// Updates `block[t] -= block[a] * block[b]^T` that column `k`'s elimination makes, for `k`
    /// in order: `updates[update_start[k]..update_start[k + 1]]`, as `[t, a, b]`.
    updates: Vec<[usize; 3]>,
    update_start: Vec<usize>,
}

impl Pattern {
    /// The pattern of an `n`-variable system whose off-diagonal blocks are `pairs` (either
    /// order; repeats and `(a, a)` allowed).
    pub fn new(n: usize, pairs: impl IntoIterator<Item = (usize, usize)>) -> Pattern {
        let mut adj = vec![BTreeSet::new(); n];
        for (a, b) in pairs {
            if a != b {
                adj[a].insert(b);
                adj[b].insert(a);
            }
        }
        // Minimum degree on the elimination graph (ties to the lower index, so the order is
        // deterministic): eliminating a variable joins its remaining neighbours into a clique,
        // and those neighbours are exactly the rows of its column in L.
        let mut queue: BTreeSet<(usize, usize)> = (0..n).map(|v| (adj[v].len(), v)).collect();
        let mut order = Vec::with_capacity(n);
        let mut neighbours = vec![Vec::new(); n];
        while let Some((_, v)) = queue.pop_first() {
            let nb: Vec<usize> = std::mem::take(&mut adj[v]).into_iter().collect();
            for &u in &nb {
                queue.remove(&(adj[u].len(), u));
                adj[u].remove(&v);
                adj[u].extend(nb.iter().copied().filter(|&w| w != u));
                queue.insert((adj[u].len(), u));
            }
            neighbours[v] = nb;
            order.push(v);
        }
        let mut position = vec![0; n];
        for (k, &v) in order.iter().enumerate() {
            position[v] = k;
        }
        let mut start = Vec::with_capacity(n + 1);
        let mut row = Vec::new();
        for (k, &v) in order.iter().enumerate() {
            start.push(row.len());
            row.push(k);
            let mut rows: Vec<usize> = neighbours[v].iter().map(|&u| position[u]).collect();
            rows.sort_unstable();
            row.extend(rows);
        }
        start.push(row.len());
        let mut p = Pattern {
            position,
            start,
            row,
            updates: Vec::new(),
            update_start: Vec::with_capacity(n + 1),
        };
        for k in 0..n {
            p.update_start.push(p.updates.len());
            let below = p.start[k] + 1..p.start[k + 1];
            for a in below.clone() {
                for b in p.start[k] + 1..=a {
                    // Block (row[a], row[b]) is in column row[b]: the elimination made it.
                    let t = p.find(p.row[b], p.row[a]);
                    p.updates.push([t, a, b]);
                }
            }
        }
        p.update_start.push(p.updates.len());
        p
    }

    /// Number of blocks (the length of the value array).
    pub fn len(&self) -> usize {
        self.row.len()
    }

    /// The block at (column position `col`, row position `row`), `row >= col`.
    fn find(&self, col: usize, row: usize) -> usize {
        let (s, e) = (self.start[col], self.start[col + 1]);
        match self.row[s..e].binary_search(&row) {
            Ok(i) => s + i,
            Err(_) => unreachable!("block ({row}, {col}) is outside the symbolic pattern"),
        }
    }

    /// The block holding `H[a][b]` (and `H[b][a]`, its transpose) for variables `a` and `b`.
    pub fn block(&self, a: usize, b: usize) -> usize {
        let (pa, pb) = (self.position[a], self.position[b]);
        self.find(pa.min(pb), pa.max(pb))
    }

    /// Factors in place: the blocks of `H` (by [`Pattern::block`], the off-diagonal ones as
    /// `H[row][col]` in elimination order, which for a symmetric block is either orientation)
    /// become those of `L` with each diagonal block stored as its inverse `L_kk^-1`. False when
    /// `H` is not positive definite.
    pub fn factor(&self, values: &mut [Matrix6<f64>]) -> bool {
        let n = self.position.len();
        for k in 0..n {
            let d = self.start[k];
            let Some(chol) = values[d].cholesky() else {
                return false;
            };
            let Some(l_inv) = chol.l().solve_lower_triangular(&Matrix6::identity()) else {
                return false;
            };
            let l_inv_t = l_inv.transpose();
            for v in &mut values[d + 1..self.start[k + 1]] {
                // L_rk = H_rk L_kk^-T.
                *v *= l_inv_t;
            }
            values[d] = l_inv;
            for &[t, a, b] in &self.updates[self.update_start[k]..self.update_start[k + 1]] {
                let u = values[a] * values[b].transpose();
                values[t] -= u;
            }
        }
        true
    }

    /// Solves `H x = rhs` (both by variable) with the factor from [`Pattern::factor`].
    pub fn solve(&self, l: &[Matrix6<f64>], rhs: &[Vector6<f64>]) -> Vec<Vector6<f64>> {
        let n = self.position.len();
        let mut y = vec![Vector6::zeros(); n];
        for (v, b) in rhs.iter().enumerate() {
            y[self.position[v]] = *b;
        }
        // L y = b, then L^T x = y.
        for k in 0..n {
            let (d, e) = (self.start[k], self.start[k + 1]);
            let yk = l[d] * y[k];
            y[k] = yk;
            for i in d + 1..e {
                y[self.row[i]] -= l[i] * yk;
            }
        }
        for k in (0..n).rev() {
            let (d, e) = (self.start[k], self.start[k + 1]);
            let mut s = y[k];
            for i in d + 1..e {
                s -= l[i].transpose() * y[self.row[i]];
            }
            y[k] = l[d].transpose() * s;
        }
        self.position.iter().map(|&p| y[p]).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use nalgebra::{DMatrix, DVector};

    /// A random symmetric positive definite system with blocks at `pairs`, as blocks for the
    /// pattern and as a dense matrix for the reference.
    fn system(
        n: usize,
        pairs: &[(usize, usize)],
        rng: &mut Rng,
    ) -> (Pattern, Vec<Matrix6<f64>>, DMatrix<f64>) {
        let p = Pattern::new(n, pairs.iter().copied());
        let mut values = vec![Matrix6::zeros(); p.len()];
        let mut dense = DMatrix::zeros(6 * n, 6 * n);
        let mut add = |a: usize, b: usize, m: &Matrix6<f64>, values: &mut Vec<Matrix6<f64>>| {
            let slot = p.block(a, b);
            // Stored as H[row][col] in elimination order.
            values[slot] += if p.position[a] >= p.position[b] {
                *m
            } else {
                m.transpose()
            };
            let mut ab = dense.view_mut((6 * a, 6 * b), (6, 6));
            ab += m;
            if a != b {
                let mut ba = dense.view_mut((6 * b, 6 * a), (6, 6));
                ba += &m.transpose();
            }
        };
        // Each pair contributes [[A, B], [B^T, C]] = J^T J for a random 6x12 J: positive
        // semi-definite; a random SPD block on every diagonal makes the sum definite.
        for &(a, b) in pairs {
            let j = nalgebra::SMatrix::<f64, 6, 12>::from_fn(|_, _| rng.uniform(-0.5, 0.5));
            let jtj = j.transpose() * j;
            let block =
                |r: usize, c: usize| -> Matrix6<f64> { jtj.fixed_view::<6, 6>(r, c).into_owned() };
            add(a, a, &block(0, 0), &mut values);
            add(b, b, &block(6, 6), &mut values);
            add(b, a, &block(6, 0), &mut values);
        }
        for v in 0..n {
            let m = Matrix6::from_fn(|_, _| rng.uniform(-0.5, 0.5));
            add(
                v,
                v,
                &(m * m.transpose() + Matrix6::identity() * 0.1),
                &mut values,
            );
        }
        (p, values, dense)
    }

    #[test]
    fn solves_like_a_dense_cholesky_on_a_chain_with_chords() {
        let mut rng = Rng::new(7);
        let n = 40;
        let mut pairs: Vec<(usize, usize)> = (1..n).map(|i| (i - 1, i)).collect();
        for _ in 0..8 {
            pairs.push((rng.below(n), rng.below(n)));
        }
        pairs.extend([(3, 30), (30, 3), (5, 5)]); // repeats and self-pairs
        let (p, mut values, dense) = system(n, &pairs, &mut rng);
        let rhs: Vec<Vector6<f64>> = (0..n)
            .map(|_| Vector6::from_fn(|_, _| rng.uniform(-0.5, 0.5)))
            .collect();
        assert!(p.factor(&mut values));
        let x = p.solve(&values, &rhs);
        let b = DVector::from_iterator(6 * n, rhs.iter().flat_map(|v| v.iter().copied()));
        let want = dense.cholesky().expect("SPD").solve(&b);
        let got = DVector::from_iterator(6 * n, x.iter().flat_map(|v| v.iter().copied()));
        let err = (got - &want).amax() / want.amax();
        assert!(err < 1e-10, "relative error {err}");
    }

    #[test]
    fn a_matrix_that_is_not_positive_definite_is_refused() {
        let mut rng = Rng::new(3);
        let (p, mut values, _) = system(3, &[(0, 1), (1, 2)], &mut rng);
        let last = p.block(2, 2);
        values[last] = -Matrix6::identity();
        assert!(!p.factor(&mut values));
    }
}
