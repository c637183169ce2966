//! A keyframe: its images as an image pyramid for coarse-to-fine training, its pose and, once
//! the encoder has produced it, its feature grid.

use super::exposure::Exposure;
use super::features::FeatureGrid;
use super::pose::PoseAdam;
use crate::camera::{Intrinsics, Pose};
use crate::Real;

/// One pyramid level: colour [h, w, 3] in [0, 1], depth [h, w] metres (0 = invalid).
#[derive(Clone, Debug)]
pub struct Level {
    pub rgb: Vec<Real>,
    pub depth: Vec<Real>,
    pub intrinsics: Intrinsics,
}

#[derive(Clone, Debug)]
pub struct Keyframe {
    pub id: u32,
    /// Camera-to-world; refined by mapping when pose learning rates are set.
    pub pose: Pose,
    /// Optimiser state of the pose.
    pub pose_adam: PoseAdam,
    /// What the camera's exposure did to this keyframe's colours (trained when enabled).
    pub exposure: Exposure,
    /// Level 0 is full resolution; level l is downsampled by 2^l.
    pub levels: Vec<Level>,
    pub features: Option<FeatureGrid>,
    /// How many mapping iterations have used this keyframe.
    pub uses: usize,
}

impl Keyframe {
    pub fn new(
        id: u32,
        rgb: Vec<Real>,
        depth: Vec<Real>,
        intrinsics: Intrinsics,
        pose: Pose,
        num_levels: usize,
    ) -> Result<Self, String> {
        intrinsics.validate()?;
        let npix = intrinsics.width * intrinsics.height;
        if rgb.len() != npix * 3 || depth.len() != npix {
            return Err(format!(
                "a {}x{} keyframe needs {} colour and {} depth values, got {} and {}",
                intrinsics.width,
                intrinsics.height,
                npix * 3,
                npix,
                rgb.len(),
                depth.len()
            ));
        }
        if pose.iter().any(|v| !v.is_finite()) {
            return Err("the keyframe pose has a non-finite entry".into());
        }
        let depth = depth
            .into_iter()
            .map(|d| if d.is_finite() && d > 0.0 { d } else { 0.0 })
            .collect();
        let mut levels = vec![Level {
            rgb,
            depth,
            intrinsics,
        }];
        while levels.len() < num_levels.max(1) {
            let prev = levels.last().unwrap();
            if prev.intrinsics.width < 2 || prev.intrinsics.height < 2 {
                break;
            }
            levels.push(downsample(prev));
        }
        Ok(Keyframe {
            id,
            pose,
            pose_adam: PoseAdam::default(),
            exposure: Exposure::default(),
            levels,
            features: None,
            uses: 0,
        })
    }

    /// Frees the images of the levels finer than `level` (at most the coarsest): a mapper that
    /// neither trains nor grows there keeps only their intrinsics. A 640x480 keyframe's full
    /// resolution is three quarters of its pyramid.
    pub fn release_below(&mut self, level: usize) {
        let keep = level.min(self.levels.len() - 1);
        for l in &mut self.levels[..keep] {
            l.rgb = Vec::new();
            l.depth = Vec::new();
        }
    }

    /// The finest level that still has its images.
    pub fn finest_kept(&self) -> usize {
        self.levels
            .iter()
            .position(|l| !l.depth.is_empty())
            .unwrap_or(0)
    }
}

/// Halves a level: colour averaged over 2x2 blocks, depth averaged over the block's valid
/// pixels (0 when none is valid), intrinsics scaled about pixel centres.
fn downsample(l: &Level) -> Level {
    let (w, h) = (l.intrinsics.width, l.intrinsics.height);
    let (w2, h2) = (w / 2, h / 2);
    let mut rgb = vec![0.0; w2 * h2 * 3];
    let mut depth = vec![0.0; w2 * h2];
    for y in 0..h2 {
        for x in 0..w2 {
            let (mut sum, mut n) = (0.0, 0.0);
            for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                let p = (2 * y + dy) * w + 2 * x + dx;
                for c in 0..3 {
                    rgb[(y * w2 + x) * 3 + c] += 0.25 * l.rgb[p * 3 + c];
                }
                if l.depth[p] > 0.0 {
                    sum += l.depth[p];
                    n += 1.0;
                }
            }
            depth[y * w2 + x] = if n > 0.0 { sum / n } else { 0.0 };
        }
    }
    let k = &l.intrinsics;
    Level {
        rgb,
        depth,
        intrinsics: Intrinsics {
            fx: k.fx / 2.0,
            fy: k.fy / 2.0,
            cx: (k.cx + 0.5) / 2.0 - 0.5,
            cy: (k.cy + 0.5) / 2.0 - 0.5,
            width: w2,
            height: h2,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pyramid_averages_colour_and_valid_depth() {
        let k = Intrinsics {
            fx: 10.0,
            fy: 10.0,
            cx: 1.5,
            cy: 1.5,
            width: 4,
            height: 4,
        };
        let rgb: Vec<Real> = (0..48).map(|i| (i % 7) as Real / 7.0).collect();
        let mut depth = vec![2.0; 16];
        depth[0] = 0.0; // invalid: the block's mean is over the three valid pixels
        depth[1] = 5.0;
        let kf = Keyframe::new(0, rgb.clone(), depth, k, Pose::identity(), 3).unwrap();
        assert_eq!(kf.levels.len(), 3);
        let l1 = &kf.levels[1];
        assert_eq!((l1.intrinsics.width, l1.intrinsics.height), (2, 2));
        assert!((l1.depth[0] - 3.0).abs() < 1e-6);
        let want = 0.25 * (rgb[0] + rgb[3] + rgb[12] + rgb[15]);
        assert!((l1.rgb[0] - want).abs() < 1e-6);
        assert!((l1.intrinsics.cx - 0.5).abs() < 1e-12);
    }

    #[test]
    fn rejects_wrong_sizes() {
        let k = Intrinsics {
            fx: 1.0,
            fy: 1.0,
            cx: 0.0,
            cy: 0.0,
            width: 2,
            height: 2,
        };
        let eye = Pose::identity();
        assert!(Keyframe::new(0, vec![0.0; 11], vec![0.0; 4], k, eye, 1).is_err());
    }
}
