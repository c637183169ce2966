//! Pinhole intrinsics (OpenCV axes: x right, y down, z forward).

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
