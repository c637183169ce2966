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

/// A 4x4 row-major rigid transform.
pub type Pose = [[f64; 4]; 4];

/// Inverse of a rigid transform [R t; 0 1]: [R^T -R^T t; 0 1].
pub fn invert_rigid(m: &Pose) -> Pose {
    let mut out = [[0.0; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = m[j][i];
        }
        out[i][3] = -(0..3).map(|j| m[j][i] * m[j][3]).sum::<f64>();
    }
    out[3][3] = 1.0;
    out
}

/// Applies a rigid transform to a point.
pub fn transform_point(m: &Pose, p: [f64; 3]) -> [f64; 3] {
    let mut out = [0.0; 3];
    for (i, o) in out.iter_mut().enumerate() {
        *o = m[i][0] * p[0] + m[i][1] * p[1] + m[i][2] * p[2] + m[i][3];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rigid_inverse_round_trips_points() {
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        let m = [
            [c, -s, 0.0, 1.0],
            [s, c, 0.0, -2.0],
            [0.0, 0.0, 1.0, 0.5],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let p = [0.2, -0.7, 3.0];
        let q = transform_point(&invert_rigid(&m), transform_point(&m, p));
        for i in 0..3 {
            assert!((p[i] - q[i]).abs() < 1e-12);
        }
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
