//! A keyframe's compressed feature grid (the encoder's patch grid after PCA), and its bilinear
//! upsampling to any image size: the feature target of the mapping loss.

use rayon::prelude::*;

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
        let coord = |p: Real, img: usize, grid: usize| {
            let s = ((p + 0.5) * grid as Real / img as Real - 0.5).clamp(0.0, (grid - 1) as Real);
            let i0 = s.floor() as usize;
            let i1 = (i0 + 1).min(grid - 1);
            (i0, i1, s - i0 as Real)
        };
        let (x0, x1, fx) = coord(x, img_w, self.width);
        let (y0, y1, fy) = coord(y, img_h, self.height);
        let k = self.k;
        let at = |xx: usize, yy: usize| &self.data[(yy * self.width + xx) * k..][..k];
        let (a, b, c, d) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
        for (i, o) in out.iter_mut().enumerate() {
            let top = a[i] + fx * (b[i] - a[i]);
            let bottom = c[i] + fx * (d[i] - c[i]);
            *o = top + fy * (bottom - top);
        }
    }

    /// The whole target at `width` x `height`: [height, width, k].
    pub fn upsample(&self, width: usize, height: usize) -> Vec<Real> {
        let mut out = Vec::new();
        self.upsample_into(width, height, &mut out);
        out
    }

    /// `upsample` into a reused buffer, rows in parallel (every mapping iteration with
    /// features makes one).
    pub fn upsample_into(&self, width: usize, height: usize, out: &mut Vec<Real>) {
        let k = self.k.max(1);
        out.resize(width * height * self.k, 0.0);
        out.par_chunks_mut((width * k).max(1))
            .enumerate()
            .for_each(|(y, row)| {
                for (x, o) in row.chunks_exact_mut(k).enumerate() {
                    self.sample(x as Real, y as Real, width, height, o);
                }
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let (gw, gh, k) = (5, 3, 4);
        let data: Vec<Real> = (0..gw * gh * k).map(|i| (i as Real * 0.37).sin()).collect();
        let g = FeatureGrid::new(data, gw, gh, k).unwrap();
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
    fn rejects_wrong_sizes_and_nan() {
        assert!(FeatureGrid::new(vec![0.0; 5], 2, 1, 3).is_err());
        assert!(FeatureGrid::new(vec![Real::NAN; 2], 2, 1, 1).is_err());
    }
}
