//! Depth seen by another camera of a rig (e.g. a Kinect's depth registered to its colour camera).

use super::{Intrinsics, Pose};

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
    let r = |i: usize, j: usize| to_from[(i, j)];
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
            let p = [0, 1, 2].map(|i| z * (col[i] + row_part[i]) + to_from[(i, 3)]);
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
        let mut m = Pose::identity();
        m[(0, 3)] = -0.05;
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
}
