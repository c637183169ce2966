//! Software prefetch: the engine's loops reach rows of large arrays (splats, features, per-pair
//! gradients, optimiser moments) in an order the hardware prefetcher cannot guess.

/// x86-64's hints for the first-level cache and for the second only (`_MM_HINT_T0`, `_T1`).
const FIRST_LEVEL: i32 = 3;
const SECOND_LEVEL: i32 = 2;

/// Asks the cache for the lines that hold `v`.
#[inline(always)]
pub(crate) fn prefetch<T>(v: &[T]) {
    lines::<FIRST_LEVEL, T>(v);
}

/// [`prefetch`] into the second-level cache only: for loops that ask for more lines at once
/// than the first level can have in flight.
#[inline(always)]
pub(crate) fn prefetch_l2<T>(v: &[T]) {
    lines::<SECOND_LEVEL, T>(v);
}

#[inline(always)]
fn lines<const HINT: i32, T>(v: &[T]) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::_mm_prefetch;
        let start = v.as_ptr() as usize;
        let end = start + std::mem::size_of_val(v);
        // From the line that holds the first byte to the one that holds the last.
        for line in (start & !63..end).step_by(64) {
            // SAFETY: prefetching never faults, whatever the address.
            unsafe { _mm_prefetch::<HINT>(line as *const i8) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = v;
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    /// The hints are the ones the intrinsics name.
    #[test]
    fn hints_are_x86s() {
        use std::arch::x86_64::{_MM_HINT_T0, _MM_HINT_T1};
        assert_eq!(
            (super::FIRST_LEVEL, super::SECOND_LEVEL),
            (_MM_HINT_T0, _MM_HINT_T1)
        );
    }
}
