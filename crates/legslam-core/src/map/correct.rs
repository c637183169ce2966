//! A pose-graph correction applied to the map without retraining it: every keyframe moves by
//! its correction, and every Gaussian rigidly with the keyframe that created it (its
//! `origin`), so that what each keyframe saw stays where that keyframe puts it.
//!
//! View-dependent colour (spherical harmonics above degree 0) is not rotated: a loop closure's
//! corrections are a few degrees, and mapping goes on training the coefficients.

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use super::Mapper;
use crate::camera::{se3, Pose};
use crate::Real;

impl Mapper {
    /// Moves keyframe `k` to `corrections[k] * pose` (a rigid world-to-world transform each),
    /// and each Gaussian made by keyframe `k` with it: its mean and its rotation. Keyframes
    /// past the end of `corrections`, and their Gaussians, stay. Returns the Gaussians moved.
    pub fn correct_keyframes(&mut self, corrections: &[Pose]) -> Result<usize, String> {
        if corrections.len() > self.keyframes.len() {
            return Err(format!(
                "{} corrections for {} keyframes",
                corrections.len(),
                self.keyframes.len()
            ));
        }
        for (k, c) in corrections.iter().enumerate() {
            se3::validate_pose(c, &format!("correction {k}"))?;
        }
        let corrections: Vec<Pose> = corrections.iter().map(se3::orthonormalize).collect();
        for (kf, c) in self.keyframes.iter_mut().zip(&corrections) {
            kf.pose = se3::orthonormalize(&(c * kf.pose));
        }
        let rotations: Vec<UnitQuaternion<f64>> = corrections
            .iter()
            .map(|c| UnitQuaternion::from_matrix(&se3::rotation(c)))
            .collect();
        let map = &mut self.map;
        let mut moved = 0;
        for (i, &k) in map.origin.iter().enumerate() {
            let Some(c) = corrections.get(k as usize) else {
                continue;
            };
            let m = &mut map.means[3 * i..3 * i + 3];
            let p = se3::transform_point(c, &Vector3::new(m[0] as f64, m[1] as f64, m[2] as f64));
            m.copy_from_slice(&[p.x as Real, p.y as Real, p.z as Real]);
            let q = &mut map.quats[4 * i..4 * i + 4];
            let old = Quaternion::new(q[0] as f64, q[1] as f64, q[2] as f64, q[3] as f64);
            let new = rotations[k as usize].into_inner() * old;
            q.copy_from_slice(&[new.w as Real, new.i as Real, new.j as Real, new.k as Real]);
            moved += 1;
        }
        Ok(moved)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::map::MapperConfig;

    fn wall(mapper: &mut Mapper, pose: Pose) -> u32 {
        let intr = Intrinsics::from_array([40.0, 40.0, 15.5, 11.5], 32, 24);
        let rgb: Vec<Real> = (0..32 * 24 * 3).map(|i| (i % 7) as Real / 7.0).collect();
        let depth = vec![2.0 as Real; 32 * 24];
        mapper.add_keyframe(rgb, depth, intr, pose).unwrap().0
    }

    fn rotation_of(q: &[Real]) -> nalgebra::Matrix3<f64> {
        let q = Quaternion::new(q[0] as f64, q[1] as f64, q[2] as f64, q[3] as f64);
        UnitQuaternion::from_quaternion(q)
            .to_rotation_matrix()
            .into_inner()
    }

    /// Every Gaussian's mean and rotation in the camera of keyframe `k`.
    fn in_camera(m: &Mapper, k: usize) -> Vec<(Vector3<f64>, nalgebra::Matrix3<f64>)> {
        let w2c = se3::inverse(&m.keyframes[k].pose);
        (0..m.map.len())
            .map(|i| {
                let p = &m.map.means[3 * i..3 * i + 3];
                let p = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                let r = rotation_of(&m.map.quats[4 * i..4 * i + 4]);
                (se3::transform_point(&w2c, &p), se3::rotation(&w2c) * r)
            })
            .collect()
    }

    fn same(
        a: &[(Vector3<f64>, nalgebra::Matrix3<f64>)],
        b: &[(Vector3<f64>, nalgebra::Matrix3<f64>)],
    ) -> bool {
        a.len() == b.len()
            && a.iter()
                .zip(b)
                .all(|((p, r), (q, s))| (p - q).norm() < 1e-5 && (r - s).abs().max() < 1e-5)
    }

    #[test]
    fn gaussians_move_rigidly_with_the_keyframe_that_made_them() {
        let mut mapper = Mapper::new(MapperConfig {
            levels: 1,
            finest_level: 0,
            grow_level: 0,
            ..Default::default()
        })
        .unwrap();
        wall(&mut mapper, Pose::identity());
        let first = mapper.map.len();
        let second_pose = se3::exp(&nalgebra::Vector6::new(0.5, 0.0, 0.0, 0.0, 0.3, 0.0));
        wall(&mut mapper, second_pose);
        assert!(first > 0 && mapper.map.len() > first);
        // Rotated Gaussians, so that their rotations are checked too.
        for (i, q) in mapper.map.quats.chunks_mut(4).enumerate() {
            let r = UnitQuaternion::from_euler_angles(0.1 * i as f64, 0.2, -0.3);
            q.copy_from_slice(&[r.w as Real, r.i as Real, r.j as Real, r.k as Real]);
        }

        // The whole map moved by one transform is the same seen from the moved keyframes.
        let before = (in_camera(&mapper, 0), in_camera(&mapper, 1));
        let c = se3::exp(&nalgebra::Vector6::new(0.1, -0.2, 0.05, 0.02, -0.04, 0.1));
        assert_eq!(mapper.correct_keyframes(&[c, c]).unwrap(), mapper.map.len());
        assert!((mapper.keyframes[1].pose - c * second_pose).abs().max() < 1e-9);
        assert!(same(&before.0, &in_camera(&mapper, 0)) && same(&before.1, &in_camera(&mapper, 1)));

        // One keyframe's correction moves its own Gaussians only: seen from it, they stay.
        let seen = in_camera(&mapper, 0);
        let moved_map = mapper.map.clone();
        let d = se3::exp(&nalgebra::Vector6::new(0.0, 0.1, 0.0, 0.05, 0.0, 0.0));
        assert_eq!(mapper.correct_keyframes(&[d]).unwrap(), first);
        assert_eq!(mapper.map.means[3 * first..], moved_map.means[3 * first..]);
        assert_eq!(mapper.map.quats[4 * first..], moved_map.quats[4 * first..]);
        assert!(same(&seen[..first], &in_camera(&mapper, 0)[..first]));
        assert!((mapper.keyframes[0].pose - d * c).abs().max() < 1e-9);

        // Too many corrections, and one that is no rigid transform, are refused.
        assert!(mapper.correct_keyframes(&[Pose::identity(); 3]).is_err());
        let mut skew = Pose::identity();
        skew[(0, 1)] = 0.5;
        let err = mapper.correct_keyframes(&[skew]).unwrap_err();
        assert!(err.contains("correction 0"), "{err}");
    }
}
