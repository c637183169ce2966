//! Row operations on structure-of-arrays buffers (row i of every array belongs to Gaussian i),
//! shared by the map's parameters and the optimiser's moments.

use rayon::prelude::*;

/// Rows a parallel task copies when gathering.
const ROWS_PER_TASK: usize = 4096;

/// Keeps the `width`-value rows of `v` where `keep` is true, in order.
pub(crate) fn retain_rows<T: Copy>(v: &mut Vec<T>, width: usize, keep: &[bool]) {
    if width == 0 {
        return;
    }
    let mut w = 0;
    for (i, &k) in keep.iter().enumerate() {
        if k {
            v.copy_within(i * width..(i + 1) * width, w * width);
            w += 1;
        }
    }
    v.truncate(w * width);
}

/// Replaces the `width`-value rows of `v` by its rows `order[0], order[1], ...` (repeats
/// allowed; every index must be a row of `v`). They are built in `spare` and copied back, so
/// that `v` keeps its buffer: a caller gathering several arrays in turn passes the same
/// `spare`, and the whole gather holds one array's worth of memory more, not a second map
/// (fresh buffers also cost more in page faults than the copies). Parallel over rows: a map's
/// reordering moves hundreds of megabytes.
pub(crate) fn gather_rows<T: Copy + Default + Send + Sync>(
    v: &mut Vec<T>,
    width: usize,
    order: &[usize],
    spare: &mut Vec<T>,
) {
    if width == 0 {
        return;
    }
    let n = order.len() * width;
    // Every value is written below: only a longer buffer's new tail needs filling first.
    spare.truncate(n);
    spare.resize(n, T::default());
    let src = &v[..];
    spare
        .par_chunks_mut(ROWS_PER_TASK * width)
        .zip(order.par_chunks(ROWS_PER_TASK))
        .for_each(|(dst, rows)| {
            for (d, &r) in dst.chunks_exact_mut(width).zip(rows) {
                d.copy_from_slice(&src[r * width..(r + 1) * width]);
            }
        });
    v.truncate(n);
    v.resize(n, T::default());
    v.par_chunks_mut(ROWS_PER_TASK * width)
        .zip(spare.par_chunks(ROWS_PER_TASK * width))
        .for_each(|(d, s)| d.copy_from_slice(s));
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rows of `width` values, row r holding r * 10 + column.
    fn rows(n: usize, width: usize) -> Vec<u32> {
        (0..n * width)
            .map(|i| (i / width * 10 + i % width) as u32)
            .collect()
    }

    #[test]
    fn gather_takes_whole_rows_in_the_order_given() {
        // More rows than a task takes, so that several tasks copy.
        let n = 3 * ROWS_PER_TASK + 5;
        for width in [1, 3, 7] {
            let mut v = rows(n, width);
            let order: Vec<usize> = (0..n + 3).map(|i| (i * 7919 + 3) % n).collect();
            // A spare holding leftovers from an earlier gather.
            let mut spare = vec![7; 11];
            gather_rows(&mut v, width, &order, &mut spare);
            let want: Vec<u32> = order
                .iter()
                .flat_map(|&r| (0..width).map(move |c| (r * 10 + c) as u32))
                .collect();
            assert_eq!(v, want, "width {width}");
        }
        let mut empty: Vec<u32> = Vec::new();
        gather_rows(&mut empty, 0, &[0, 1], &mut Vec::new());
        assert!(empty.is_empty());
    }

    #[test]
    fn retain_keeps_the_flagged_rows_in_order() {
        let mut v = rows(5, 2);
        retain_rows(&mut v, 2, &[true, false, false, true, true]);
        assert_eq!(v, vec![0, 1, 30, 31, 40, 41]);
    }
}
