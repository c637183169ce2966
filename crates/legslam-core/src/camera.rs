//! Pinhole intrinsics (OpenCV axes: x right, y down, z forward), rigid poses, and depth moved
//! from one camera to another.

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

/// The depth image a second camera (`to`, e.g. the colour camera of an RGB-D rig) sees, from
/// the depth image `depth` of the camera `from` and the rigid motion `to_from` taking `from`'s
/// points into `to`'s (translation in the depth's unit). Each depth pixel is lifted, moved and
/// projected to the nearest pixel; where several land on one pixel the nearest surface wins.
/// 0 in and out means no depth. Returns `to.width * to.height` values, row-major.
pub fn register_depth(
    depth: &[f32],
    from: Intrinsics,
    to: Intrinsics,
    to_from: &Pose,
) -> Result<Vec<f32>, String> {
    from.validate()?;
    to.validate()?;
    if depth.len() != from.width * from.height {
        return Err(format!(
            "a {}x{} depth image has {} values, got {}",
            from.width,
            from.height,
            from.width * from.height,
            depth.len()
        ));
    }
    let mut out = vec![f32::INFINITY; to.width * to.height];
    // p = z * (R * ray) + t with ray = (x, y, 1): R * ray is a column part plus a row part.
    let r = |i: usize, j: usize| to_from[i][j];
    let columns: Vec<[f64; 3]> = (0..from.width)
        .map(|u| {
            let x = (u as f64 - from.cx) / from.fx;
            [r(0, 0) * x, r(1, 0) * x, r(2, 0) * x]
        })
        .collect();
    for (v, row) in depth.chunks_exact(from.width).enumerate() {
        let y = (v as f64 - from.cy) / from.fy;
        let row_part = [0, 1, 2].map(|i| r(i, 1) * y + r(i, 2));
        for (&z, col) in row.iter().zip(&columns) {
            if !(z > 0.0 && z.is_finite()) {
                continue;
            }
            let z = f64::from(z);
            let p = [0, 1, 2].map(|i| z * (col[i] + row_part[i]) + to_from[i][3]);
            if p[2] <= 0.0 {
                continue;
            }
            let inv = 1.0 / p[2];
            // The nearest pixel, halves rounding up: floor(x + 0.5) by truncation, which is
            // a floor for x + 0.5 >= 0 (and much cheaper than a rounding call).
            let (uc, vc) = (
                to.fx * p[0] * inv + to.cx + 0.5,
                to.fy * p[1] * inv + to.cy + 0.5,
            );
            if !(uc >= 0.0 && vc >= 0.0 && uc < to.width as f64 && vc < to.height as f64) {
                continue;
            }
            let o = &mut out[vc as usize * to.width + uc as usize];
            *o = o.min(p[2] as f32);
        }
    }
    for o in &mut out {
        if o.is_infinite() {
            *o = 0.0;
        }
    }
    Ok(out)
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
    fn registered_depth_of_a_wall_shifts_by_the_parallax() {
        // A wall 2 m away over the right 50 columns; the second camera 5 cm to the right sees
        // it 400 * 0.05 / 2 = 10 pixels further left, at the same depth.
        let k = Intrinsics::from_array([400.0, 400.0, 39.5, 19.5], 80, 40);
        let mut depth = vec![0.0f32; 80 * 40];
        for (i, d) in depth.iter_mut().enumerate() {
            if i % 80 >= 30 {
                *d = 2.0;
            }
        }
        let m = [
            [1.0, 0.0, 0.0, -0.05],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let out = register_depth(&depth, k, k, &m).unwrap();
        for (i, &z) in out.iter().enumerate() {
            let expected = if (20..70).contains(&(i % 80)) {
                2.0
            } else {
                0.0
            };
            assert!((z - expected).abs() < 1e-6, "pixel {i}: {z}");
        }
        let small = Intrinsics::from_array([400.0, 400.0, 39.5, 19.5], 80, 39);
        assert!(register_depth(&depth, small, k, &m)
            .unwrap_err()
            .contains("80x39"));
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
