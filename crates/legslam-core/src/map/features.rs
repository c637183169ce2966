//! A keyframe's compressed feature grid (the encoder's patch grid after PCA), and its bilinear
//! upsampling to any image size: the feature target of the mapping loss.

use crate::loss::{blend, Blend};
use crate::Real;

#[derive(Clone, Debug)]
pub struct FeatureGrid {
    /// [height, width, k]
    pub data: Vec<Real>,
    pub width: usize,
    pub height: usize,
    pub k: usize,
}

impl FeatureGrid {
    pub fn new(data: Vec<Real>, width: usize, height: usize, k: usize) -> Result<Self, String> {
        if width == 0 || height == 0 || data.len() != width * height * k {
            return Err(format!(
                "a feature grid of {width}x{height}x{k} needs {} values, got {}",
                width * height * k,
                data.len()
            ));
        }
        if data.iter().any(|v| !v.is_finite()) {
            return Err("the feature grid has a non-finite value".into());
        }
        Ok(FeatureGrid {
            data,
            width,
            height,
            k,
        })
    }

    /// The feature at pixel (x, y) of an image of `img_w` x `img_h` covering the same view,
    /// with pixel centres aligned (as `align_corners=False`), edges repeated.
    pub fn sample(&self, x: Real, y: Real, img_w: usize, img_h: usize, out: &mut [Real]) {
        let (x0, x1, fx) = cells(x, img_w, self.width);
        let (y0, y1, fy) = cells(y, img_h, self.height);
        let k = self.k;
        let at = |xx: usize, yy: usize| &self.data[(yy * self.width + xx) * k..][..k];
        let (a, b, c, d) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
        for (i, o) in out.iter_mut().enumerate() {
            *o = blend(blend(a[i], b[i], fx), blend(c[i], d[i], fx), fy);
        }
    }

    /// The whole target at `width` x `height`: [height, width, k].
    pub fn upsample(&self, width: usize, height: usize) -> Vec<Real> {
        let mut out = vec![0.0; width * height * self.k];
        for (p, o) in out.chunks_exact_mut(self.k.max(1)).enumerate() {
            self.sample((p % width) as Real, (p / width) as Real, width, height, o);
        }
        out
    }

    /// The target at `width` x `height` as the feature loss reads it
    /// ([`FeatureTarget::Blended`](crate::loss::FeatureTarget)): the grid's rows upsampled to
    /// `width` along x in `rows` ([grid height, width, k]), and which two of them each pixel
    /// row blends in `blends`; the same values as [`FeatureGrid::upsample`], bit for bit, at
    /// a fraction of the cost (every mapping iteration with features makes one).
    pub fn blended_into(
        &self,
        width: usize,
        height: usize,
        rows: &mut Vec<Real>,
        blends: &mut Vec<Blend>,
    ) {
        self.sampled_into(width, height, None, rows, blends)
    }

    /// [`Self::blended_into`] at the points (s x + o[0], s y + o[1]) of an image
    /// `full[0]` x `full[1]` (`at` = (s, o, full)) instead of the pixels' centres.
    pub fn sampled_into(
        &self,
        width: usize,
        height: usize,
        at: Option<(Real, [Real; 2], [usize; 2])>,
        rows: &mut Vec<Real>,
        blends: &mut Vec<Blend>,
    ) {
        let place = |p: usize, img: usize, axis: usize| match at {
            Some((s, o, full)) => (s * p as Real + o[axis], full[axis]),
            None => (p as Real, img),
        };
        let k = self.k;
        rows.resize(self.height * width * k, 0.0);
        for (gy, row) in rows.chunks_exact_mut((width * k).max(1)).enumerate() {
            let grid_row = &self.data[gy * self.width * k..][..self.width * k];
            for (x, o) in row.chunks_exact_mut(k.max(1)).enumerate() {
                let (px, img) = place(x, width, 0);
                let (x0, x1, fx) = cells(px, img, self.width);
                let (a, b) = (&grid_row[x0 * k..][..k], &grid_row[x1 * k..][..k]);
                for ((o, &a), &b) in o.iter_mut().zip(a).zip(b) {
                    *o = blend(a, b, fx);
                }
            }
        }
        blends.clear();
        blends.extend((0..height).map(|y| {
            let (py, img) = place(y, height, 1);
            let (lower, upper, weight) = cells(py, img, self.height);
            Blend {
                lower,
                upper,
                weight,
            }
        }));
    }
}

/// Where pixel coordinate `p` of an image `img` pixels across falls on a grid `grid` cells
/// across (pixel centres aligned, edges repeated): the two cells it blends and the second's
/// share.
fn cells(p: Real, img: usize, grid: usize) -> (usize, usize, Real) {
    let s = ((p + 0.5) * grid as Real / img as Real - 0.5).clamp(0.0, (grid - 1) as Real);
    let i0 = s.floor() as usize;
    let i1 = (i0 + 1).min(grid - 1);
    (i0, i1, s - i0 as Real)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 5x3 grid of 4 channels, every value different.
    fn wavy_grid() -> FeatureGrid {
        let (gw, gh, k) = (5, 3, 4);
        let data: Vec<Real> = (0..gw * gh * k).map(|i| (i as Real * 0.37).sin()).collect();
        FeatureGrid::new(data, gw, gh, k).unwrap()
    }

    #[test]
    fn upsampling_interpolates_between_cell_centres_and_repeats_edges() {
        // 2x1 grid, one channel: values 0 and 1 at cell centres. Upsampled to 4 pixels wide,
        // pixel centres map to grid x = (p + 0.5) / 2 - 0.5 = -0.25, 0.25, 0.75, 1.25.
        let g = FeatureGrid::new(vec![0.0, 1.0], 2, 1, 1).unwrap();
        let up = g.upsample(4, 1);
        let expect = [0.0, 0.25, 0.75, 1.0];
        for (a, b) in up.iter().zip(expect) {
            assert!((a - b).abs() < 1e-6, "{up:?}");
        }
    }

    #[test]
    fn upsampling_is_the_sample_at_every_pixel() {
        let g = wavy_grid();
        let k = g.k;
        let (w, h) = (23, 17);
        let up = g.upsample(w, h);
        assert_eq!(up.len(), w * h * k);
        let mut one = vec![0.0; k];
        for y in 0..h {
            for x in 0..w {
                g.sample(x as Real, y as Real, w, h, &mut one);
                assert_eq!(&up[(y * w + x) * k..][..k], &one[..], "pixel ({x}, {y})");
            }
        }
        assert!(g.upsample(0, 0).is_empty());
    }

    #[test]
    fn blended_rows_expand_to_the_upsampled_target_bit_for_bit() {
        let g = wavy_grid();
        let (gh, k) = (g.height, g.k);
        let (mut rows, mut blends) = (Vec::new(), Vec::new());
        // Finer and coarser than the grid, and the grid's own size.
        for (w, h) in [(23, 17), (3, 2), (5, 3)] {
            g.blended_into(w, h, &mut rows, &mut blends);
            assert_eq!((rows.len(), blends.len()), (gh * w * k, h));
            let up = g.upsample(w, h);
            for (y, b) in blends.iter().enumerate() {
                for x in 0..w * k {
                    let (lo, hi) = (rows[b.lower * w * k + x], rows[b.upper * w * k + x]);
                    let v = blend(lo, hi, b.weight);
                    assert_eq!(
                        v.to_bits(),
                        up[y * w * k + x].to_bits(),
                        "{w}x{h} ({x}, {y})"
                    );
                }
            }
        }
    }

    #[test]
    fn sampled_rows_are_the_grid_at_the_points() {
        let g = wavy_grid();
        let (gh, k) = (g.height, g.k);
        let (mut rows, mut blends) = (Vec::new(), Vec::new());
        let mut one = vec![0.0; k];
        for (s, o, full) in [(2.0, [0.0, 1.0], [23, 17]), (4.0, [-0.5, 2.9], [40, 30])] {
            let (w, h) = (full[0] / s as usize, full[1] / s as usize);
            g.sampled_into(w, h, Some((s, o, full)), &mut rows, &mut blends);
            assert_eq!((rows.len(), blends.len()), (gh * w * k, h));
            for (y, b) in blends.iter().enumerate() {
                for x in 0..w {
                    let (px, py) = (s * x as Real + o[0], s * y as Real + o[1]);
                    g.sample(px, py, full[0], full[1], &mut one);
                    for (c, want) in one.iter().enumerate() {
                        let at = |row: usize| rows[(row * w + x) * k + c];
                        let v = blend(at(b.lower), at(b.upper), b.weight);
                        assert_eq!(v.to_bits(), want.to_bits(), "s {s} ({x}, {y})");
                    }
                }
            }
        }
    }

    #[test]
    fn rejects_wrong_sizes_and_nan() {
        assert!(FeatureGrid::new(vec![0.0; 5], 2, 1, 3).is_err());
        assert!(FeatureGrid::new(vec![Real::NAN; 2], 2, 1, 1).is_err());
    }
}
