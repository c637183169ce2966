//! The map's row order: Gaussians near each other in space near each other in memory.
//!
//! A tile's list reaches its Gaussians' splats, features and gradient rows by index. Rows in
//! the order they were made (keyframe after keyframe, clones and splits at the end) scatter a
//! tile's Gaussians over the whole map, and every walk of a list pays cache and TLB misses for
//! it; along a space-filling curve, a tile's Gaussians lie in a few runs of rows, and so do a
//! view's rows that the optimiser steps.

use crate::Real;

/// Bits of each coordinate in a Morton code (three of them fill 63 bits).
const BITS: u32 = 21;

/// The rows where `keep` is true, ordered along a Morton (Z-order) curve through their means'
/// bounding box (ties by row). Coordinates that are not finite count as the box's low corner.
pub fn spatial_order(means: &[Real], keep: &[bool]) -> Vec<usize> {
    let mut lo = [Real::INFINITY; 3];
    let mut hi = [Real::NEG_INFINITY; 3];
    for (m, _) in means.chunks_exact(3).zip(keep).filter(|(_, &k)| k) {
        for a in 0..3 {
            if m[a].is_finite() {
                lo[a] = lo[a].min(m[a]);
                hi[a] = hi[a].max(m[a]);
            }
        }
    }
    let cells = ((1u64 << BITS) - 1) as f64;
    let cell = |v: Real, a: usize| -> u64 {
        let span = f64::from(hi[a]) - f64::from(lo[a]);
        let t = (f64::from(v) - f64::from(lo[a])) / span * cells;
        // NaN (a box of zero span) is cell 0, as a coordinate that is not finite.
        if !v.is_finite() || t.is_nan() {
            0
        } else {
            t.clamp(0.0, cells) as u64
        }
    };
    let mut keyed: Vec<(u64, usize)> = means
        .chunks_exact(3)
        .zip(keep)
        .enumerate()
        .filter(|(_, (_, &k))| k)
        .map(|(i, (m, _))| {
            let code = (0..3).fold(0, |code, a| code | spread(cell(m[a], a)) << a);
            (code, i)
        })
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// The low 21 bits of `x` at every third bit (bit b to bit 3b).
fn spread(x: u64) -> u64 {
    let mut x = x & ((1 << BITS) - 1);
    x = (x | x << 32) & 0x001f_0000_0000_ffff;
    x = (x | x << 16) & 0x001f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    (x | x << 2) & 0x1249_2492_4924_9249
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn spread_puts_each_bit_three_apart() {
        let mut rng = Rng::new(3);
        for _ in 0..1000 {
            let x = (rng.next_f64() * (1u64 << BITS) as f64) as u64;
            let plain = (0..BITS).fold(0, |s, b| s | ((x >> b) & 1) << (3 * b));
            assert_eq!(spread(x), plain, "x = {x:#x}");
        }
        assert_eq!(
            spread(u64::MAX),
            spread((1 << BITS) - 1),
            "bits above 21 ignored"
        );
    }

    /// Points in the eight octants of a cube, shuffled: the order takes each octant's points
    /// together, octants in Morton order (x the lowest bit), and leaves out unkept rows.
    #[test]
    fn orders_by_octant_and_leaves_out_dropped_rows() {
        let mut rng = Rng::new(4);
        let mut means = Vec::new();
        let mut octant = Vec::new();
        for i in 0..400 {
            let o = (i * 5) % 8;
            for a in 0..3 {
                let high = (o >> a) & 1 == 1;
                let v = rng.next_f64() * 0.9 + if high { 1.05 } else { 0.05 };
                means.push(v as Real);
            }
            octant.push(o);
        }
        // The box's corners, so that octants split at 1.0 exactly.
        means.extend_from_slice(&[0.0, 0.0, 0.0, 2.0, 2.0, 2.0]);
        octant.extend([0, 7]);
        let keep: Vec<bool> = (0..octant.len()).map(|i| i % 7 != 3).collect();
        let order = spatial_order(&means, &keep);
        let kept: Vec<usize> = (0..keep.len()).filter(|&i| keep[i]).collect();
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, kept, "a permutation of the kept rows");
        let octants: Vec<usize> = order.iter().map(|&i| octant[i]).collect();
        assert!(
            octants.windows(2).all(|w| w[0] <= w[1]),
            "octants in Morton order: {octants:?}"
        );
        // A coordinate that is not finite neither panics nor drops its row, and counts as the
        // box's low side: row 1, high in x and z, infinite in y, sorts with the octant high
        // in x and z alone (5), before every row of octant 6 (high in y and z).
        means[0] = Real::NAN;
        means[3..6].copy_from_slice(&[1.5, Real::INFINITY, 1.5]);
        let again = spatial_order(&means, &keep);
        let mut sorted = again.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, kept);
        let at = |row: usize| again.iter().position(|&r| r == row).unwrap();
        assert!(
            (0..octant.len()).all(|r| octant[r] != 6 || !keep[r] || at(1) < at(r)),
            "row 1 sorted as if its y were high"
        );
    }

    /// On points scattered through a room, consecutive rows end up far closer in space than in
    /// the order the points came in.
    #[test]
    fn consecutive_rows_are_near() {
        let mut rng = Rng::new(5);
        let n = 5000;
        let means: Vec<Real> = (0..3 * n).map(|_| (rng.next_f64() * 4.0) as Real).collect();
        let gap = |order: &[usize]| -> f64 {
            order
                .windows(2)
                .map(|w| {
                    (0..3)
                        .map(|a| f64::from(means[3 * w[0] + a] - means[3 * w[1] + a]).powi(2))
                        .sum::<f64>()
                        .sqrt()
                })
                .sum::<f64>()
                / (order.len() - 1) as f64
        };
        let before = gap(&(0..n).collect::<Vec<_>>());
        let after = gap(&spatial_order(&means, &vec![true; n]));
        assert!(after < before / 8.0, "mean step {after} against {before}");
    }
}
