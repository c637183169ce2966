//! The camera: pinhole intrinsics (OpenCV axes: x right, y down, z forward), the one pose type
//! of the engine with its SE(3) algebra ([`se3`]), and depth moved from one camera to another
//! ([`register_depth`]).

mod register;
pub mod se3;

pub use register::register_depth;

/// A rigid transform as a 4x4 homogeneous matrix: camera-to-world (`T_wc`) unless a name says
/// otherwise (`w2c`, `to_from`). The engine's only pose type at its interfaces; hot loops copy
/// what they need into `glam` types.
pub type Pose = nalgebra::Matrix4<f64>;

/// Intrinsics in pixels of the image they belong to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: usize,
    pub height: usize,
}

impl Intrinsics {
    /// From (fx, fy, cx, cy) and the image size.
    pub fn from_array([fx, fy, cx, cy]: [f64; 4], width: usize, height: usize) -> Self {
        Intrinsics {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        }
    }

    /// Images larger than this many pixels (134 million, 11585 x 11585) are refused before
    /// anything is allocated for them.
    pub const MAX_PIXELS: usize = 1 << 27;

    /// Checks that the intrinsics describe a usable camera.
    pub fn validate(&self) -> Result<(), String> {
        let finite = [self.fx, self.fy, self.cx, self.cy]
            .iter()
            .all(|v| v.is_finite());
        if !finite {
            return Err(format!("intrinsics must be finite, got {self:?}"));
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(format!(
                "focal lengths must be positive, got fx={} fy={}",
                self.fx, self.fy
            ));
        }
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "image size must be non-zero, got {}x{}",
                self.width, self.height
            ));
        }
        if self.width.saturating_mul(self.height) > Self::MAX_PIXELS {
            return Err(format!(
                "a {}x{} image is too large: at most {} pixels",
                self.width,
                self.height,
                Self::MAX_PIXELS
            ));
        }
        Ok(())
    }

    /// The same camera for an image scaled by `s` (e.g. 0.5 for half resolution), following
    /// the pixel-centre convention of `cv2.resize`.
    pub fn scaled(&self, s: f64) -> Intrinsics {
        Intrinsics {
            fx: self.fx * s,
            fy: self.fy * s,
            cx: (self.cx + 0.5) * s - 0.5,
            cy: (self.cy + 0.5) * s - 0.5,
            width: ((self.width as f64) * s).round().max(1.0) as usize,
            height: ((self.height as f64) * s).round().max(1.0) as usize,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_image_too_large_to_allocate_is_refused_by_its_size() {
        let k = Intrinsics::from_array([500.0, 500.0, 0.0, 0.0], 100_000, 100_000);
        assert!(k
            .validate()
            .unwrap_err()
            .contains("100000x100000 image is too large"));
    }

    #[test]
    fn half_scale_keeps_pixel_centres_aligned() {
        let k = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 319.5,
            cy: 239.5,
            width: 640,
            height: 480,
        };
        let h = k.scaled(0.5);
        assert_eq!((h.width, h.height), (320, 240));
        assert!((h.cx - 159.5).abs() < 1e-12 && (h.fx - 250.0).abs() < 1e-12);
    }
}
