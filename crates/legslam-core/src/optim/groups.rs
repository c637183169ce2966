//! One value per parameter group, in the map's order.

use crate::raster::Gradients;
use crate::Real;

/// Something per parameter group of the Gaussians: slices of parameters or gradients,
/// learning rates, row widths.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Groups<T> {
    /// [N, 3]
    pub means: T,
    /// [N, 3]
    pub log_scales: T,
    /// [N, 4]
    pub quats: T,
    /// [N]
    pub opacity_logits: T,
    /// [N, C, 3]
    pub sh: T,
    /// [N, K]
    pub features: T,
}

/// Group names in the order of [`Groups::into_array`], for error messages.
pub(crate) const NAMES: [&str; 6] = [
    "means",
    "log_scales",
    "quats",
    "opacity_logits",
    "sh",
    "features",
];

/// Group names as the mapper's `lr_` options spell them (`lr_opacity`), in the same order:
/// what callers name a group by.
pub const LR_NAMES: [&str; 6] = ["means", "log_scales", "quats", "opacity", "sh", "features"];

impl<T> Groups<T> {
    pub fn into_array(self) -> [T; 6] {
        [
            self.means,
            self.log_scales,
            self.quats,
            self.opacity_logits,
            self.sh,
            self.features,
        ]
    }

    pub fn from_array([means, log_scales, quats, opacity_logits, sh, features]: [T; 6]) -> Self {
        Groups {
            means,
            log_scales,
            quats,
            opacity_logits,
            sh,
            features,
        }
    }

    pub fn map<U>(self, f: impl FnMut(T) -> U) -> Groups<U> {
        Groups::from_array(self.into_array().map(f))
    }

    /// `f` of each group's pair.
    pub fn zip<U, V>(self, o: Groups<U>, mut f: impl FnMut(T, U) -> V) -> Groups<V> {
        let mut o = o.into_array().into_iter();
        self.map(|a| f(a, o.next().expect("six groups")))
    }
}

impl<T: Copy> Groups<T> {
    /// `v` for every group.
    pub fn splat(v: T) -> Self {
        Groups::from_array([v; 6])
    }
}

/// The parameter-group gradients of a rasterizer backward pass.
impl<'a> From<&'a Gradients> for Groups<&'a [Real]> {
    fn from(g: &'a Gradients) -> Self {
        Groups {
            means: &g.means,
            log_scales: &g.log_scales,
            quats: &g.quats,
            opacity_logits: &g.opacity_logits,
            sh: &g.sh,
            features: &g.features,
        }
    }
}
