//! The Gaussian map's storage: structure-of-arrays rows that grow, shrink and duplicate
//! together.

use crate::optim::Groups;
use crate::raster::Gaussians;
use crate::rows::{gather_rows, retain_rows};
use crate::Real;

/// N Gaussians, row i of every array belonging to Gaussian i.
#[derive(Clone, Debug, Default)]
pub struct GaussianMap {
    pub means: Vec<Real>,
    pub log_scales: Vec<Real>,
    pub quats: Vec<Real>,
    pub opacity_logits: Vec<Real>,
    pub sh: Vec<Real>,
    pub features: Vec<Real>,
    /// Per Gaussian: the keyframe it was created from (to give it a feature once that
    /// keyframe's features are ready).
    pub origin: Vec<u32>,
    /// Per Gaussian: whether its feature has been set from a target.
    pub has_feature: Vec<bool>,
    pub sh_coeffs: usize,
    pub num_features: usize,
}

/// One new Gaussian.
pub struct NewGaussian<'a> {
    pub mean: [Real; 3],
    pub log_scale: [Real; 3],
    pub quat: [Real; 4],
    pub opacity_logit: Real,
    /// sh_coeffs x 3
    pub sh: &'a [Real],
    /// num_features values, or empty when no feature is known yet.
    pub feature: &'a [Real],
    pub origin: u32,
}

impl GaussianMap {
    pub fn new(sh_coeffs: usize, num_features: usize) -> Self {
        GaussianMap {
            sh_coeffs,
            num_features,
            ..Default::default()
        }
    }

    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn view(&self) -> Gaussians<'_> {
        Gaussians {
            means: &self.means,
            log_scales: &self.log_scales,
            quats: &self.quats,
            opacity_logits: &self.opacity_logits,
            sh: &self.sh,
            sh_coeffs: self.sh_coeffs,
            features: &self.features,
            num_features: self.num_features,
        }
    }

    /// The trainable arrays, as the optimiser takes them.
    pub fn params_mut(&mut self) -> Groups<&mut [Real]> {
        Groups {
            means: &mut self.means,
            log_scales: &mut self.log_scales,
            quats: &mut self.quats,
            opacity_logits: &mut self.opacity_logits,
            sh: &mut self.sh,
            features: &mut self.features,
        }
    }

    /// The parameter arrays with their row widths, for operations applied to all alike.
    fn groups_mut(&mut self) -> [(&mut Vec<Real>, usize); 6] {
        let (c, k) = (self.sh_coeffs * 3, self.num_features);
        [
            (&mut self.means, 3),
            (&mut self.log_scales, 3),
            (&mut self.quats, 4),
            (&mut self.opacity_logits, 1),
            (&mut self.sh, c),
            (&mut self.features, k),
        ]
    }

    pub fn push(&mut self, g: NewGaussian) {
        debug_assert_eq!(g.sh.len(), self.sh_coeffs * 3);
        self.means.extend_from_slice(&g.mean);
        self.log_scales.extend_from_slice(&g.log_scale);
        self.quats.extend_from_slice(&g.quat);
        self.opacity_logits.push(g.opacity_logit);
        self.sh.extend_from_slice(g.sh);
        if g.feature.len() == self.num_features {
            self.features.extend_from_slice(g.feature);
            self.has_feature.push(self.num_features > 0);
        } else {
            self.features
                .extend(std::iter::repeat_n(0.0, self.num_features));
            self.has_feature.push(false);
        }
        self.origin.push(g.origin);
    }

    /// Keeps the rows where `keep` is true, in order.
    pub fn retain(&mut self, keep: &[bool]) {
        assert_eq!(keep.len(), self.len());
        for (v, w) in self.groups_mut() {
            retain_rows(v, w, keep);
        }
        retain_rows(&mut self.origin, 1, keep);
        retain_rows(&mut self.has_feature, 1, keep);
    }

    /// Replaces the rows by rows `order[0], order[1], ...` (as [`crate::optim::Adam::gather`];
    /// every index must be a row).
    pub fn gather(&mut self, order: &[usize]) {
        let groups = self.groups_mut();
        let widest = groups.iter().map(|(_, w)| *w).max().unwrap_or(0);
        let mut spare = Vec::with_capacity(order.len() * widest);
        for (v, w) in groups {
            gather_rows(v, w, order, &mut spare);
        }
        gather_rows(&mut self.origin, 1, order, &mut Vec::new());
        gather_rows(&mut self.has_feature, 1, order, &mut Vec::new());
    }

    /// Appends copies of the rows `rows` (for clone and split densification).
    pub fn duplicate(&mut self, rows: &[usize]) {
        for (v, w) in self.groups_mut() {
            duplicate_rows(v, w, rows);
        }
        duplicate_rows(&mut self.origin, 1, rows);
        duplicate_rows(&mut self.has_feature, 1, rows);
    }
}

fn duplicate_rows<T: Copy>(v: &mut Vec<T>, width: usize, rows: &[usize]) {
    v.reserve(rows.len() * width);
    for &r in rows {
        v.extend_from_within(r * width..(r + 1) * width);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map_with(n: usize) -> GaussianMap {
        let mut m = GaussianMap::new(1, 2);
        for i in 0..n {
            let f = i as Real;
            let feature = [f, -f];
            m.push(NewGaussian {
                mean: [f, f + 0.1, f + 0.2],
                log_scale: [-f; 3],
                quat: [1.0, 0.0, 0.0, 0.0],
                opacity_logit: f,
                sh: &[f, 2.0 * f, 3.0 * f],
                feature: if i % 2 == 0 { &feature } else { &[] },
                origin: i as u32,
            });
        }
        m
    }

    #[test]
    fn rows_stay_together_through_retain_and_duplicate() {
        let mut m = map_with(5);
        m.retain(&[true, false, true, false, true]);
        assert_eq!(m.len(), 3);
        assert_eq!(m.opacity_logits, vec![0.0, 2.0, 4.0]);
        assert_eq!(&m.means[3..6], &[2.0, 2.1, 2.2]);
        assert_eq!(&m.sh[6..9], &[4.0, 8.0, 12.0]);
        assert_eq!(&m.features[2..4], &[2.0, -2.0]);
        assert_eq!(m.origin, vec![0, 2, 4]);
        m.duplicate(&[2, 0]);
        assert_eq!(m.opacity_logits, vec![0.0, 2.0, 4.0, 4.0, 0.0]);
        assert_eq!(&m.features[6..8], &[4.0, -4.0]);
        assert_eq!(m.means.len(), 15);
        assert_eq!(m.has_feature, vec![true, true, true, true, true]);
        m.view().validate().unwrap();
    }

    #[test]
    fn missing_features_are_zero_and_flagged() {
        let m = map_with(2);
        assert_eq!(&m.features[2..4], &[0.0, 0.0]);
        assert_eq!(m.has_feature, vec![true, false]);
    }
}
