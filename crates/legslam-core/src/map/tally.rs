//! A running sum and count per Gaussian between two refinements of the map: densification
//! tallies screen-space gradient norms, pruning the contributions to the views.

use crate::Real;

#[derive(Clone, Debug, Default)]
pub struct Tally {
    pub sum: Vec<Real>,
    pub count: Vec<u32>,
}

impl Tally {
    /// Adds `value` to Gaussian `i`'s sum and counts it once (`i` within `resize`'s rows).
    pub fn add(&mut self, i: usize, value: Real) {
        self.sum[i] += value;
        self.count[i] += 1;
    }

    /// How many values Gaussian `i` has had; 0 for rows beyond the tally (appended since).
    pub fn count(&self, i: usize) -> u32 {
        self.count.get(i).copied().unwrap_or(0)
    }

    /// The mean of Gaussian `i`'s values, None when it has had none.
    pub fn mean(&self, i: usize) -> Option<Real> {
        let n = self.count(i);
        (n > 0).then(|| self.sum[i] / n as Real)
    }

    /// Covers `n` Gaussians, the new rows with nothing tallied.
    pub fn resize(&mut self, n: usize) {
        self.sum.resize(n, 0.0);
        self.count.resize(n, 0);
    }

    /// Starts again from nothing for `n` Gaussians.
    pub fn reset(&mut self, n: usize) {
        self.sum.clear();
        self.count.clear();
        self.resize(n);
    }
}
