//! Eight pixels at a time: the operations the compositing kernels are written in, as a trait
//! with four implementations. [`Portable`] works on plain arrays and runs everywhere (the
//! fallback, and the reference the others are tested against); [`Avx2`] uses AVX2 registers and
//! is chosen at run time where an x86-64 CPU has them; [`Avx512`] is the same code compiled
//! with AVX-512VL, whose 32 vector registers hold what AVX2's 16 spill (chosen where the CPU
//! has it); [`Neon`] uses two NEON registers, which every aarch64 CPU has. All perform the same
//! IEEE operations in the same order (no fused multiply-add; the same polynomial `exp`; the
//! same tree for horizontal sums), so a kernel gives identical bits on any of them.

use crate::Real;

/// Pixels per lane vector.
pub(crate) const LANES: usize = 8;

/// Which implementation of [`Lanes`] the rasterizer runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Simd {
    /// The CPU's vector path ([`native_simd`]) where it has one, else portable.
    #[default]
    Auto,
    /// The portable implementation, on any CPU.
    Portable,
    /// AVX2 (an error where the CPU lacks it, or in f64 builds).
    Avx2,
    /// AVX2's operations on the same eight lanes, compiled with AVX-512F and VL: twice the
    /// vector registers, the same bits (an error where the CPU lacks them, or in f64 builds).
    Avx512,
    /// NEON (an error off aarch64, or in f64 builds).
    Neon,
}

impl Simd {
    /// The implementation to run: `Portable`, `Avx2`, `Avx512` or `Neon`.
    pub fn resolve(self) -> Result<Simd, String> {
        match self {
            Simd::Auto => Ok(native_simd().unwrap_or(Simd::Portable)),
            Simd::Avx2 if !avx2_available() => {
                Err("this CPU (or an f64 build) has no AVX2 rasterizer path".into())
            }
            Simd::Avx512 if !avx512_available() => {
                Err("this CPU (or an f64 build) has no AVX-512 rasterizer path".into())
            }
            Simd::Neon if !neon_available() => {
                Err("this CPU (or an f64 build) has no NEON rasterizer path".into())
            }
            s => Ok(s),
        }
    }

    /// The implementation's name, as benchmarks print it.
    pub fn name(self) -> &'static str {
        match self {
            Simd::Auto => "auto",
            Simd::Portable => "portable",
            Simd::Avx2 => "avx2",
            Simd::Avx512 => "avx512",
            Simd::Neon => "neon",
        }
    }
}

/// The vector implementation this CPU runs best (`Avx512`, `Avx2` or `Neon`), if it has one.
pub fn native_simd() -> Option<Simd> {
    vector_paths().last().copied()
}

/// Every vector implementation this CPU can run, slowest first (tests compare each with the
/// portable one).
pub fn vector_paths() -> Vec<Simd> {
    [
        (Simd::Neon, neon_available()),
        (Simd::Avx2, avx2_available()),
        (Simd::Avx512, avx512_available()),
    ]
    .into_iter()
    .filter_map(|(simd, here)| here.then_some(simd))
    .collect()
}

/// Whether the AVX2 path can run here (never in f64 builds: it is an f32 kernel).
pub fn avx2_available() -> bool {
    #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(all(target_arch = "x86_64", not(feature = "f64"))))]
    {
        false
    }
}

/// Whether the AVX-512 path can run here: AVX2 with AVX-512F and VL (Intel since Skylake-SP,
/// AMD since Zen 4), never in f64 builds.
pub fn avx512_available() -> bool {
    #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
    {
        avx2_available()
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512vl")
    }
    #[cfg(not(all(target_arch = "x86_64", not(feature = "f64"))))]
    {
        false
    }
}

/// Whether the NEON path can run here: on every aarch64 CPU (NEON is part of the
/// architecture's base), never in f64 builds.
pub fn neon_available() -> bool {
    cfg!(all(target_arch = "aarch64", not(feature = "f64")))
}

/// The body of a kernel's dispatch: `kernel::<L>(args)` through the implementation `simd`
/// chose (see [`Simd::resolve`]), each x86-64 vector path through an entry point compiled with
/// its own CPU features, so that the kernel inlined into it is too.
macro_rules! dispatch {
    ($simd:expr, $kernel:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)?) => {{
        #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
        {
            /// # Safety
            /// The CPU must support AVX2.
            #[target_feature(enable = "avx2")]
            #[allow(clippy::too_many_arguments)]
            unsafe fn avx2($($arg: $ty),*) $(-> $ret)? {
                $kernel::<$crate::raster::lanes::Avx2>($($arg),*)
            }
            /// # Safety
            /// The CPU must support AVX2, AVX-512F and AVX-512VL.
            #[target_feature(enable = "avx2,avx512f,avx512vl")]
            #[allow(clippy::too_many_arguments)]
            unsafe fn avx512($($arg: $ty),*) $(-> $ret)? {
                $kernel::<$crate::raster::lanes::Avx512>($($arg),*)
            }
            match $simd {
                // SAFETY: `Simd::resolve` chose each only where the CPU has it.
                $crate::raster::Simd::Avx2 => return unsafe { avx2($($arg),*) },
                $crate::raster::Simd::Avx512 => return unsafe { avx512($($arg),*) },
                _ => {}
            }
        }
        #[cfg(all(target_arch = "aarch64", not(feature = "f64")))]
        if $simd == $crate::raster::Simd::Neon {
            return $kernel::<$crate::raster::lanes::Neon>($($arg),*);
        }
        let _ = $simd;
        $kernel::<$crate::raster::lanes::Portable>($($arg),*)
    }};
}
pub(crate) use dispatch;

/// Eight lanes of `Real` and the operations on them.
pub(crate) trait Lanes: Copy {
    type Mask: Copy;
    fn splat(v: Real) -> Self;
    fn load(s: &[Real]) -> Self;
    fn store(self, s: &mut [Real]);
    fn add(self, o: Self) -> Self;
    fn sub(self, o: Self) -> Self;
    fn mul(self, o: Self) -> Self;
    fn div(self, o: Self) -> Self;
    fn min(self, o: Self) -> Self;
    /// `self` where `self > o`, else `o` (as `maxps`).
    fn max(self, o: Self) -> Self;
    fn sqrt(self) -> Self;
    /// Each lane rounded toward zero, for lanes in [0, 2^24] (where `as u32` is exact).
    #[inline(always)]
    fn trunc(self) -> Self {
        let mut v = [0.0; LANES];
        self.store(&mut v);
        // Not `Real::trunc`, an out-of-line call without SSE4.1.
        Self::load(&v.map(|x| (x as u32) as Real))
    }
    /// Lanes holding integers in [0, 2^24] as integers.
    #[inline(always)]
    fn to_u32(self) -> [u32; LANES] {
        let mut v = [0.0; LANES];
        self.store(&mut v);
        v.map(|x| x as u32)
    }
    fn lt(self, o: Self) -> Self::Mask;
    fn le(self, o: Self) -> Self::Mask;
    fn gt(self, o: Self) -> Self::Mask;
    /// Lanes where `end[l] > j`.
    fn below(j: u32, end: &[u32]) -> Self::Mask;
    fn and(a: Self::Mask, b: Self::Mask) -> Self::Mask;
    /// `a` and not `b`.
    fn and_not(a: Self::Mask, b: Self::Mask) -> Self::Mask;
    /// Bit l set where lane l is set.
    fn bits(m: Self::Mask) -> u32;
    /// `a` where `m`, else `b`.
    fn select(m: Self::Mask, a: Self, b: Self) -> Self;
    /// `out[l] = v` where `m`.
    fn set_where(m: Self::Mask, v: u32, out: &mut [u32]);
    /// `select(m, self, old)` into `out`, where `old` was loaded from `out`.
    #[inline(always)]
    fn store_where(self, m: Self::Mask, old: Self, out: &mut [Real]) {
        Self::select(m, self, old).store(out)
    }
    /// e^x, for x <= 0 (the falloff of a Gaussian), to 1.75e-7 relative error.
    fn exp(self) -> Self;
    /// e^x over the range a Gaussian's parameters take: x clamped to [-87, 88].
    fn exp_wide(self) -> Self;
    /// ln x for positive finite x; below the smallest normal number (or NaN) x is taken as
    /// that number.
    fn ln(self) -> Self;
    /// Eight consecutive rows of `stride` values (`rows[l * stride + c]`, `rows` at least
    /// `8 * stride` long) as columns: `out[c]`'s lane l is row l's value c, for the first
    /// `out.len()` columns (at most `stride`).
    #[inline(always)]
    fn load_columns(rows: &[Real], stride: usize, out: &mut [Self]) {
        assert!(out.len() <= stride && rows.len() >= LANES * stride);
        for (c, o) in out.iter_mut().enumerate() {
            let mut v = [0.0; LANES];
            for (l, x) in v.iter_mut().enumerate() {
                *x = rows[l * stride + c];
            }
            *o = Self::load(&v);
        }
    }
    /// The sum of the lanes, as ((0 + 4) + (2 + 6)) + ((1 + 5) + (3 + 7)).
    fn hsum(self) -> Real;
    /// `hsum` of eight vectors at once (the same sums, bit for bit).
    #[inline(always)]
    fn hsum8(v: [Self; 8]) -> [Real; 8] {
        v.map(Self::hsum)
    }
    /// `out[i] += w * f[i]` over equally long slices.
    fn axpy(out: &mut [Real], w: Real, f: &[Real]);
    /// The dot product of two equally long slices: eight partial sums, then `hsum`, then the
    /// tail in order.
    fn dot(a: &[Real], b: &[Real]) -> Real;
    /// `axpy(out, w, g)` and `dot(g, f)` in one pass over `g` (the same bits as the two), the
    /// dot product left as its eight partial sums and its tail: `hsum` of the first plus the
    /// second (so that a caller can reduce eight of them in one [`Lanes::hsum8`]). `FRESH`:
    /// `out` is taken to hold zeros, and is not read (the same bits as zeroing it first).
    #[inline(always)]
    fn axpy_dot<const FRESH: bool>(
        out: &mut [Real],
        w: Real,
        g: &[Real],
        f: &[Real],
    ) -> (Self, Real) {
        let n = out.len().min(g.len()).min(f.len());
        let full = n - n % LANES;
        let (wv, mut acc) = (Self::splat(w), Self::splat(0.0));
        for ((o, g), f) in out[..full]
            .chunks_exact_mut(LANES)
            .zip(g[..full].chunks_exact(LANES))
            .zip(f[..full].chunks_exact(LANES))
        {
            let gv = Self::load(g);
            let old = if FRESH {
                Self::splat(0.0)
            } else {
                Self::load(o)
            };
            old.add(wv.mul(gv)).store(o);
            acc = acc.add(gv.mul(Self::load(f)));
        }
        let mut tail = 0.0;
        for ((o, g), f) in out[full..n].iter_mut().zip(&g[full..n]).zip(&f[full..n]) {
            *o = if FRESH { 0.0 } else { *o } + w * g;
            tail += g * f;
        }
        (acc, tail)
    }
}

/// The polynomial e^x and ln x every implementation evaluates (Cephes' expf: x = n ln2 + r, a
/// degree-5 polynomial in r, 2^n from the exponent bits, or a degree-3 one for the falloff;
/// and its logf), for the f32 engine.
/// Lanes left over from a masked-out computation may hold anything: the clamps keep them
/// finite.
#[cfg(not(feature = "f64"))]
mod expf {
    pub const LOG2E: f32 = std::f32::consts::LOG2_E;
    /// ln 2 in two parts, so that n * LN2_HI is exact.
    pub const LN2_HI: f32 = 0.693_359_4;
    pub const LN2_LO: f32 = -2.121_944_4e-4;
    /// Adding and subtracting 1.5 * 2^23 rounds to the nearest integer (ties to even).
    pub const ROUND: f32 = 12_582_912.0;
    pub const LOW: f32 = -87.0;
    pub const HIGH: f32 = 0.0;
    /// The wide exponential's upper clamp: e^88 is below f32's largest value.
    pub const WIDE_HIGH: f32 = 88.0;
    /// The falloff's polynomial, two degrees lower: fitted to the relative error of e^r over
    /// the reduced range (Lawson's iteration, then rounded to f32), 1.75e-7 at most with the
    /// range reduction against Cephes' 6e-8. The compositing waits on this chain of dependent
    /// operations, and alpha needs no more.
    pub const P_FALLOFF: [f32; 4] = [8.312_504e-3, 4.189_033_8e-2, 1.666_711_6e-1, 4.999_923e-1];
    pub const P: [f32; 6] = [
        1.987_569_1e-4,
        1.398_199_9e-3,
        8.333_452e-3,
        4.166_579_6e-2,
        1.666_666_5e-1,
        0.5,
    ];

    /// Cephes' logf: x = m 2^e with m in [sqrt(1/2), sqrt(2)), a degree-8 polynomial in m - 1.
    pub const SQRT_HALF: f32 = std::f32::consts::FRAC_1_SQRT_2;
    pub const LOG_P: [f32; 9] = [
        7.037_683_6e-2,
        -1.151_461e-1,
        1.167_699_9e-1,
        -1.242_014_1e-1,
        1.424_932_3e-1,
        -1.666_805_8e-1,
        2.000_071_5e-1,
        -2.499_999_4e-1,
        3.333_333e-1,
    ];
    pub const MANTISSA: u32 = 0x007f_ffff;
    /// The exponent bits of 0.5.
    pub const HALF_BITS: u32 = 0x3f00_0000;

    #[inline(always)]
    pub fn ln(x: f32) -> f32 {
        // As maxps, for the same bits on every input.
        let x = if x > f32::MIN_POSITIVE {
            x
        } else {
            f32::MIN_POSITIVE
        };
        let bits = x.to_bits();
        let e = ((bits >> 23) as i32 - 126) as f32;
        let m = f32::from_bits((bits & MANTISSA) | HALF_BITS);
        let small = m < SQRT_HALF;
        let e = e - if small { 1.0 } else { 0.0 };
        let m = if small { m + m } else { m } - 1.0;
        let z = m * m;
        let mut y = LOG_P[0];
        for c in &LOG_P[1..] {
            y = y * m + c;
        }
        let y = y * m * z + e * LN2_LO - z * 0.5;
        (m + y) + e * LN2_HI
    }

    #[inline(always)]
    pub fn exp(x: f32, high: f32, poly: &[f32]) -> f32 {
        // As maxps then minps, for the same bits on every input.
        let x = if x > LOW { x } else { LOW };
        let x = if x < high { x } else { high };
        let n = (x * LOG2E + ROUND) - ROUND;
        let r = (x - n * LN2_HI) - n * LN2_LO;
        let mut p = poly[0];
        for c in &poly[1..] {
            p = p * r + c;
        }
        let y = (p * (r * r) + r) + 1.0;
        y * f32::from_bits(((n as i32 + 127) as u32) << 23)
    }
}

/// Plain arrays: the portable implementation.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Portable([Real; LANES]);

impl Portable {
    #[inline(always)]
    fn map(self, f: impl Fn(Real) -> Real) -> Self {
        Portable(std::array::from_fn(|l| f(self.0[l])))
    }

    #[inline(always)]
    fn zip(self, o: Self, f: impl Fn(Real, Real) -> Real) -> Self {
        Portable(std::array::from_fn(|l| f(self.0[l], o.0[l])))
    }

    #[inline(always)]
    fn test(self, o: Self, f: impl Fn(Real, Real) -> bool) -> [bool; LANES] {
        std::array::from_fn(|l| f(self.0[l], o.0[l]))
    }
}

impl Lanes for Portable {
    type Mask = [bool; LANES];

    #[inline(always)]
    fn splat(v: Real) -> Self {
        Portable([v; LANES])
    }
    #[inline(always)]
    fn load(s: &[Real]) -> Self {
        Portable(s[..LANES].try_into().unwrap())
    }
    #[inline(always)]
    fn store(self, s: &mut [Real]) {
        s[..LANES].copy_from_slice(&self.0);
    }
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        self.zip(o, |a, b| a + b)
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        self.zip(o, |a, b| a - b)
    }
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        self.zip(o, |a, b| a * b)
    }
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        self.zip(o, |a, b| a / b)
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        // As minps: the second operand when they compare false (equal, or NaN).
        self.zip(o, |a, b| if a < b { a } else { b })
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        self.zip(o, |a, b| if a > b { a } else { b })
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        self.map(Real::sqrt)
    }
    #[inline(always)]
    fn lt(self, o: Self) -> [bool; LANES] {
        self.test(o, |a, b| a < b)
    }
    #[inline(always)]
    fn le(self, o: Self) -> [bool; LANES] {
        self.test(o, |a, b| a <= b)
    }
    #[inline(always)]
    fn gt(self, o: Self) -> [bool; LANES] {
        self.test(o, |a, b| a > b)
    }
    #[inline(always)]
    fn below(j: u32, end: &[u32]) -> [bool; LANES] {
        std::array::from_fn(|l| end[l] > j)
    }
    #[inline(always)]
    fn and(a: [bool; LANES], b: [bool; LANES]) -> [bool; LANES] {
        std::array::from_fn(|l| a[l] & b[l])
    }
    #[inline(always)]
    fn and_not(a: [bool; LANES], b: [bool; LANES]) -> [bool; LANES] {
        std::array::from_fn(|l| a[l] & !b[l])
    }
    #[inline(always)]
    fn bits(m: [bool; LANES]) -> u32 {
        m.iter()
            .enumerate()
            .fold(0, |acc, (l, &b)| acc | (u32::from(b) << l))
    }
    #[inline(always)]
    fn select(m: [bool; LANES], a: Self, b: Self) -> Self {
        Portable(std::array::from_fn(|l| if m[l] { a.0[l] } else { b.0[l] }))
    }
    #[inline(always)]
    fn set_where(m: [bool; LANES], v: u32, out: &mut [u32]) {
        for (o, &set) in out[..LANES].iter_mut().zip(&m) {
            if set {
                *o = v;
            }
        }
    }
    #[inline(always)]
    fn exp(self) -> Self {
        #[cfg(not(feature = "f64"))]
        return self.map(|x| expf::exp(x, expf::HIGH, &expf::P_FALLOFF));
        #[cfg(feature = "f64")]
        return self.map(Real::exp);
    }
    #[inline(always)]
    fn exp_wide(self) -> Self {
        #[cfg(not(feature = "f64"))]
        return self.map(|x| expf::exp(x, expf::WIDE_HIGH, &expf::P));
        #[cfg(feature = "f64")]
        return self.map(Real::exp);
    }
    #[inline(always)]
    fn ln(self) -> Self {
        #[cfg(not(feature = "f64"))]
        return self.map(expf::ln);
        #[cfg(feature = "f64")]
        return self.map(|x| x.max(Real::MIN_POSITIVE).ln());
    }
    #[inline(always)]
    fn hsum(self) -> Real {
        let v = self.0;
        ((v[0] + v[4]) + (v[2] + v[6])) + ((v[1] + v[5]) + (v[3] + v[7]))
    }
    #[inline(always)]
    fn axpy(out: &mut [Real], w: Real, f: &[Real]) {
        for (o, v) in out.iter_mut().zip(f) {
            *o += w * v;
        }
    }
    #[inline(always)]
    fn dot(a: &[Real], b: &[Real]) -> Real {
        let mut acc = Portable::splat(0.0);
        let (ca, cb) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
        let tail = ca
            .remainder()
            .iter()
            .zip(cb.remainder())
            .fold(0.0, |s, (x, y)| s + x * y);
        for (x, y) in ca.zip(cb) {
            acc = acc.add(Portable::load(x).mul(Portable::load(y)));
        }
        acc.hsum() + tail
    }
}

#[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
pub(crate) use avx2::{Avx2, Avx512};

#[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
mod avx2 {
    //! Every function here is only ever inlined into code compiled with AVX2 enabled (the
    //! `#[target_feature]` entry points of the kernels), which callers reach only after
    //! checking the CPU ([`super::Simd::resolve`]).
    use std::arch::x86_64::*;

    use super::{expf, Lanes, LANES};

    /// Eight f32 lanes in an AVX register. `EVEX` tells the kernels compiled with AVX-512VL
    /// (32 registers, mask registers) from those compiled with AVX2 alone: the operations are
    /// the same, but a kernel instantiated for one type is compiled with one set of features,
    /// so each entry point gets code of its own (with one type shared by both, the closures
    /// inside a kernel were compiled once, outside either entry and without AVX2).
    #[derive(Clone, Copy, Debug)]
    pub(crate) struct Avx<const EVEX: bool>(__m256);

    pub(crate) type Avx2 = Avx<false>;
    pub(crate) type Avx512 = Avx<true>;

    /// `v`, hidden from the optimiser: LLVM turns a blend of new lanes into what was loaded
    /// from an address, stored back there, into a masked store (`vmaskmovps`), which Zen 2
    /// and 3 run far slower than the load, blend and store (on Zen 3 the raster bench's
    /// forward at K = 0 took 111-119 ms with it, 90-102 ms without).
    #[inline]
    #[target_feature(enable = "avx")]
    fn opaque(mut v: __m256) -> __m256 {
        // SAFETY: an empty instruction string: `v` stays in its register, unchanged.
        unsafe { std::arch::asm!("/* {0} */", inout(ymm_reg) v, options(pure, nomem, nostack)) };
        v
    }

    /// The polynomial exponential of `expf`, clamped to [LOW, high].
    #[inline(always)]
    fn exp8(x: __m256, high: f32, poly: &[f32]) -> __m256 {
        unsafe {
            let s = _mm256_set1_ps;
            let x = _mm256_min_ps(_mm256_max_ps(x, s(expf::LOW)), s(high));
            // One rounding instruction for the portable path's add and subtract of ROUND: the
            // same integer (ties to even) for every clamped x.
            let n = _mm256_round_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(
                _mm256_mul_ps(x, s(expf::LOG2E)),
            );
            let r = _mm256_sub_ps(
                _mm256_sub_ps(x, _mm256_mul_ps(n, s(expf::LN2_HI))),
                _mm256_mul_ps(n, s(expf::LN2_LO)),
            );
            let mut p = s(poly[0]);
            for c in &poly[1..] {
                p = _mm256_add_ps(_mm256_mul_ps(p, r), s(*c));
            }
            let y = _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(p, _mm256_mul_ps(r, r)), r),
                s(1.0),
            );
            let e = _mm256_slli_epi32::<23>(_mm256_add_epi32(
                _mm256_cvtps_epi32(n),
                _mm256_set1_epi32(127),
            ));
            _mm256_mul_ps(y, _mm256_castsi256_ps(e))
        }
    }

    /// The eight values of `rows` from `at`, zeros past its end.
    #[inline(always)]
    fn row8(rows: &[f32], at: usize) -> __m256 {
        if at + LANES <= rows.len() {
            // SAFETY: the eight values lie inside the slice.
            unsafe { _mm256_loadu_ps(rows.as_ptr().add(at)) }
        } else {
            let mut v = [0.0; LANES];
            let n = rows.len().saturating_sub(at);
            v[..n].copy_from_slice(&rows[at..at + n]);
            unsafe { _mm256_loadu_ps(v.as_ptr()) }
        }
    }

    /// Eight rows of eight values as eight columns.
    #[inline(always)]
    fn transpose8(r: [__m256; 8]) -> [__m256; 8] {
        unsafe {
            let t = [
                _mm256_unpacklo_ps(r[0], r[1]),
                _mm256_unpackhi_ps(r[0], r[1]),
                _mm256_unpacklo_ps(r[2], r[3]),
                _mm256_unpackhi_ps(r[2], r[3]),
                _mm256_unpacklo_ps(r[4], r[5]),
                _mm256_unpackhi_ps(r[4], r[5]),
                _mm256_unpacklo_ps(r[6], r[7]),
                _mm256_unpackhi_ps(r[6], r[7]),
            ];
            let u = [
                _mm256_shuffle_ps::<0x44>(t[0], t[2]),
                _mm256_shuffle_ps::<0xEE>(t[0], t[2]),
                _mm256_shuffle_ps::<0x44>(t[1], t[3]),
                _mm256_shuffle_ps::<0xEE>(t[1], t[3]),
                _mm256_shuffle_ps::<0x44>(t[4], t[6]),
                _mm256_shuffle_ps::<0xEE>(t[4], t[6]),
                _mm256_shuffle_ps::<0x44>(t[5], t[7]),
                _mm256_shuffle_ps::<0xEE>(t[5], t[7]),
            ];
            [
                _mm256_permute2f128_ps::<0x20>(u[0], u[4]),
                _mm256_permute2f128_ps::<0x20>(u[1], u[5]),
                _mm256_permute2f128_ps::<0x20>(u[2], u[6]),
                _mm256_permute2f128_ps::<0x20>(u[3], u[7]),
                _mm256_permute2f128_ps::<0x31>(u[0], u[4]),
                _mm256_permute2f128_ps::<0x31>(u[1], u[5]),
                _mm256_permute2f128_ps::<0x31>(u[2], u[6]),
                _mm256_permute2f128_ps::<0x31>(u[3], u[7]),
            ]
        }
    }

    /// Eight rows of three values (24 in a row) as their three columns: each column's lanes
    /// come from the three vectors in turn (lane i from vector (i + k) % 3 for column k), so a
    /// blend of the three puts them in place up to one permutation.
    #[inline(always)]
    fn deinterleave3(rows: &[f32]) -> [__m256; 3] {
        assert!(rows.len() >= 24);
        unsafe {
            let p = rows.as_ptr();
            let (a, b, c) = (
                _mm256_loadu_ps(p),
                _mm256_loadu_ps(p.add(8)),
                _mm256_loadu_ps(p.add(16)),
            );
            // x: a at lanes 0, 3, 6; b at 1, 4, 7; c at 2, 5.
            let x = _mm256_blend_ps::<0b0010_0100>(_mm256_blend_ps::<0b1001_0010>(a, b), c);
            // y: c at 0, 3, 6; a at 1, 4, 7; b at 2, 5.
            let y = _mm256_blend_ps::<0b0010_0100>(_mm256_blend_ps::<0b1001_0010>(c, a), b);
            // z: b at 0, 3, 6; c at 1, 4, 7; a at 2, 5.
            let z = _mm256_blend_ps::<0b0010_0100>(_mm256_blend_ps::<0b1001_0010>(b, c), a);
            [
                _mm256_permutevar8x32_ps(x, _mm256_setr_epi32(0, 3, 6, 1, 4, 7, 2, 5)),
                _mm256_permutevar8x32_ps(y, _mm256_setr_epi32(1, 4, 7, 2, 5, 0, 3, 6)),
                _mm256_permutevar8x32_ps(z, _mm256_setr_epi32(2, 5, 0, 3, 6, 1, 4, 7)),
            ]
        }
    }

    impl<const EVEX: bool> Lanes for Avx<EVEX> {
        type Mask = __m256;

        #[inline(always)]
        fn splat(v: f32) -> Self {
            unsafe { Self(_mm256_set1_ps(v)) }
        }
        #[inline(always)]
        fn load(s: &[f32]) -> Self {
            assert!(s.len() >= LANES);
            unsafe { Self(_mm256_loadu_ps(s.as_ptr())) }
        }
        #[inline(always)]
        fn store(self, s: &mut [f32]) {
            assert!(s.len() >= LANES);
            unsafe { _mm256_storeu_ps(s.as_mut_ptr(), self.0) }
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            unsafe { Self(_mm256_add_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            unsafe { Self(_mm256_sub_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            unsafe { Self(_mm256_mul_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn div(self, o: Self) -> Self {
            unsafe { Self(_mm256_div_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            unsafe { Self(_mm256_min_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            unsafe { Self(_mm256_max_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            unsafe { Self(_mm256_sqrt_ps(self.0)) }
        }
        #[inline(always)]
        fn trunc(self) -> Self {
            unsafe { Self(_mm256_round_ps::<{ _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC }>(self.0)) }
        }
        #[inline(always)]
        fn to_u32(self) -> [u32; LANES] {
            let mut out = [0; LANES];
            // SAFETY: `out` holds eight u32s.
            unsafe {
                let v = _mm256_cvttps_epi32(self.0);
                _mm256_storeu_si256(out.as_mut_ptr() as *mut __m256i, v);
            }
            out
        }
        #[inline(always)]
        fn lt(self, o: Self) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_LT_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn le(self, o: Self) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_LE_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn gt(self, o: Self) -> __m256 {
            unsafe { _mm256_cmp_ps::<_CMP_GT_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn below(j: u32, end: &[u32]) -> __m256 {
            assert!(end.len() >= LANES);
            // Signed compare: tile lists are far shorter than 2^31.
            unsafe {
                let e = _mm256_loadu_si256(end.as_ptr() as *const __m256i);
                _mm256_castsi256_ps(_mm256_cmpgt_epi32(e, _mm256_set1_epi32(j as i32)))
            }
        }
        #[inline(always)]
        fn and(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_and_ps(a, b) }
        }
        #[inline(always)]
        fn and_not(a: __m256, b: __m256) -> __m256 {
            unsafe { _mm256_andnot_ps(b, a) }
        }
        #[inline(always)]
        fn bits(m: __m256) -> u32 {
            unsafe { _mm256_movemask_ps(m) as u32 }
        }
        #[inline(always)]
        fn select(m: __m256, a: Self, b: Self) -> Self {
            unsafe { Self(_mm256_blendv_ps(b.0, a.0, m)) }
        }
        #[inline(always)]
        fn store_where(self, m: __m256, old: Self, out: &mut [f32]) {
            Self::select(m, self, Self(unsafe { opaque(old.0) })).store(out)
        }
        #[inline(always)]
        fn set_where(m: __m256, v: u32, out: &mut [u32]) {
            assert!(out.len() >= LANES);
            unsafe {
                let p = out.as_mut_ptr() as *mut __m256i;
                let old = opaque(_mm256_castsi256_ps(_mm256_loadu_si256(p)));
                let new = _mm256_castsi256_ps(_mm256_set1_epi32(v as i32));
                _mm256_storeu_si256(p, _mm256_castps_si256(_mm256_blendv_ps(old, new, m)));
            }
        }
        #[inline(always)]
        fn exp(self) -> Self {
            Self(exp8(self.0, expf::HIGH, &expf::P_FALLOFF))
        }
        #[inline(always)]
        fn exp_wide(self) -> Self {
            Self(exp8(self.0, expf::WIDE_HIGH, &expf::P))
        }
        #[inline(always)]
        fn ln(self) -> Self {
            unsafe {
                let s = _mm256_set1_ps;
                let i = _mm256_set1_epi32;
                let x = _mm256_max_ps(self.0, s(f32::MIN_POSITIVE));
                let bits = _mm256_castps_si256(x);
                let e = _mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_srli_epi32::<23>(bits), i(126)));
                let m = _mm256_castsi256_ps(_mm256_or_si256(
                    _mm256_and_si256(bits, i(expf::MANTISSA as i32)),
                    i(expf::HALF_BITS as i32),
                ));
                let small = _mm256_cmp_ps::<_CMP_LT_OQ>(m, s(expf::SQRT_HALF));
                let e = _mm256_sub_ps(e, _mm256_and_ps(small, s(1.0)));
                let m = _mm256_sub_ps(_mm256_blendv_ps(m, _mm256_add_ps(m, m), small), s(1.0));
                let z = _mm256_mul_ps(m, m);
                let mut y = s(expf::LOG_P[0]);
                for c in &expf::LOG_P[1..] {
                    y = _mm256_add_ps(_mm256_mul_ps(y, m), s(*c));
                }
                let y = _mm256_sub_ps(
                    _mm256_add_ps(
                        _mm256_mul_ps(_mm256_mul_ps(y, m), z),
                        _mm256_mul_ps(e, s(expf::LN2_LO)),
                    ),
                    _mm256_mul_ps(z, s(0.5)),
                );
                Self(_mm256_add_ps(
                    _mm256_add_ps(m, y),
                    _mm256_mul_ps(e, s(expf::LN2_HI)),
                ))
            }
        }
        /// By eight-by-eight transpositions in registers (a gather per column costs several
        /// times more on AMD's cores), three-row deinterleaving for rows of three.
        #[inline(always)]
        fn load_columns(rows: &[f32], stride: usize, out: &mut [Self]) {
            let width = out.len();
            assert!(width <= stride && rows.len() >= LANES * stride);
            if stride == 3 && width == 3 {
                let [x, y, z] = deinterleave3(rows);
                (out[0], out[1], out[2]) = (Self(x), Self(y), Self(z));
                return;
            }
            for c0 in (0..width).step_by(LANES) {
                let row = |l: usize| l * stride + c0;
                let cols = transpose8([
                    row8(rows, row(0)),
                    row8(rows, row(1)),
                    row8(rows, row(2)),
                    row8(rows, row(3)),
                    row8(rows, row(4)),
                    row8(rows, row(5)),
                    row8(rows, row(6)),
                    row8(rows, row(7)),
                ]);
                for (o, v) in out[c0..].iter_mut().zip(cols) {
                    *o = Self(v);
                }
            }
        }
        #[inline(always)]
        fn hsum(self) -> f32 {
            unsafe {
                let s = _mm_add_ps(
                    _mm256_castps256_ps128(self.0),
                    _mm256_extractf128_ps::<1>(self.0),
                );
                let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
                _mm_cvtss_f32(_mm_add_ss(s, _mm_shuffle_ps::<1>(s, s)))
            }
        }
        /// A transposition instead of eight reductions: halves added pairwise across
        /// vectors, then the same tree as `hsum` in every lane.
        #[inline(always)]
        fn hsum8(v: [Self; 8]) -> [f32; 8] {
            unsafe {
                // [a0+a4, a1+a5, a2+a6, a3+a7 | the same of b] for the pairs (a, b).
                let halves = |a: __m256, b: __m256| {
                    _mm256_add_ps(
                        _mm256_permute2f128_ps::<0x20>(a, b),
                        _mm256_permute2f128_ps::<0x31>(a, b),
                    )
                };
                let (ab, cd) = (halves(v[0].0, v[1].0), halves(v[2].0, v[3].0));
                let (ef, gh) = (halves(v[4].0, v[5].0), halves(v[6].0, v[7].0));
                // [a02, c02, a13, c13 | b02, d02, b13, d13], where a02 = (a0+a4) + (a2+a6).
                let quarters = |x: __m256, y: __m256| {
                    _mm256_add_ps(_mm256_unpacklo_ps(x, y), _mm256_unpackhi_ps(x, y))
                };
                let (abcd, efgh) = (quarters(ab, cd), quarters(ef, gh));
                // [a, c, e, g | b, d, f, h], each a02 + a13.
                let sums = _mm256_add_ps(
                    _mm256_shuffle_ps::<0x44>(abcd, efgh),
                    _mm256_shuffle_ps::<0xEE>(abcd, efgh),
                );
                let mut out = [0.0; 8];
                _mm256_storeu_ps(out.as_mut_ptr(), sums);
                // Spelt out: `array::map` would be a call, with bounds checks, per pair.
                [
                    out[0], out[4], out[1], out[5], out[2], out[6], out[3], out[7],
                ]
            }
        }
        #[inline(always)]
        fn axpy(out: &mut [f32], w: f32, f: &[f32]) {
            let n = out.len().min(f.len());
            let mut i = 0;
            unsafe {
                let wv = _mm256_set1_ps(w);
                while i + LANES <= n {
                    let o = out.as_mut_ptr().add(i);
                    let v = _mm256_mul_ps(wv, _mm256_loadu_ps(f.as_ptr().add(i)));
                    _mm256_storeu_ps(o, _mm256_add_ps(_mm256_loadu_ps(o), v));
                    i += LANES;
                }
            }
            for (o, v) in out[i..n].iter_mut().zip(&f[i..n]) {
                *o += w * v;
            }
        }
        #[inline(always)]
        fn dot(a: &[f32], b: &[f32]) -> f32 {
            let n = a.len().min(b.len());
            let mut i = 0;
            let mut acc = Self::splat(0.0);
            unsafe {
                while i + LANES <= n {
                    let x = _mm256_loadu_ps(a.as_ptr().add(i));
                    let y = _mm256_loadu_ps(b.as_ptr().add(i));
                    acc = Self(_mm256_add_ps(acc.0, _mm256_mul_ps(x, y)));
                    i += LANES;
                }
            }
            let tail = a[i..n]
                .iter()
                .zip(&b[i..n])
                .fold(0.0, |s, (x, y)| s + x * y);
            acc.hsum() + tail
        }
    }
}

#[cfg(all(target_arch = "aarch64", not(feature = "f64")))]
pub(crate) use neon::Neon;

#[cfg(all(target_arch = "aarch64", not(feature = "f64")))]
#[allow(unused_unsafe)] // some NEON intrinsics are safe to call, depending on the Rust version
mod neon {
    //! NEON is part of aarch64's base architecture, so these run on every CPU of the target.
    //! Eight lanes are two quad registers, lanes 0-3 in the first. Minimum and the exponential's
    //! clamps are compares and selects, as `minps` and `maxps` treat NaN and equal operands
    //! (NEON's `fmin` and `fmax` do not).
    use std::arch::aarch64::*;

    use super::{expf, Lanes, LANES};

    #[derive(Clone, Copy, Debug)]
    pub(crate) struct Neon(float32x4_t, float32x4_t);

    #[derive(Clone, Copy, Debug)]
    pub(crate) struct Mask(uint32x4_t, uint32x4_t);

    impl Neon {
        #[inline(always)]
        fn zip(self, o: Self, f: impl Fn(float32x4_t, float32x4_t) -> float32x4_t) -> Self {
            Neon(f(self.0, o.0), f(self.1, o.1))
        }

        #[inline(always)]
        fn test(self, o: Self, f: impl Fn(float32x4_t, float32x4_t) -> uint32x4_t) -> Mask {
            Mask(f(self.0, o.0), f(self.1, o.1))
        }
    }

    /// `a` where `a < b`, else `b` (as `minps`).
    #[inline(always)]
    fn min4(a: float32x4_t, b: float32x4_t) -> float32x4_t {
        unsafe { vbslq_f32(vcltq_f32(a, b), a, b) }
    }

    /// `a` where `a > b`, else `b` (as `maxps`).
    #[inline(always)]
    fn max4(a: float32x4_t, b: float32x4_t) -> float32x4_t {
        unsafe { vbslq_f32(vcgtq_f32(a, b), a, b) }
    }

    #[inline(always)]
    fn exp4(x: float32x4_t, high: f32, poly: &[f32]) -> float32x4_t {
        unsafe {
            let s = vdupq_n_f32;
            let x = min4(max4(x, s(expf::LOW)), s(high));
            // As AVX2's: one rounding instruction (ties to even) for the add and subtract.
            let n = vrndnq_f32(vmulq_f32(x, s(expf::LOG2E)));
            let r = vsubq_f32(
                vsubq_f32(x, vmulq_f32(n, s(expf::LN2_HI))),
                vmulq_f32(n, s(expf::LN2_LO)),
            );
            let mut p = s(poly[0]);
            for c in &poly[1..] {
                p = vaddq_f32(vmulq_f32(p, r), s(*c));
            }
            let y = vaddq_f32(vaddq_f32(vmulq_f32(p, vmulq_f32(r, r)), r), s(1.0));
            // n is a whole number: truncating it converts it exactly.
            let e = vshlq_n_s32::<23>(vaddq_s32(vcvtq_s32_f32(n), vdupq_n_s32(127)));
            vmulq_f32(y, vreinterpretq_f32_s32(e))
        }
    }

    #[inline(always)]
    fn ln4(x: float32x4_t) -> float32x4_t {
        unsafe {
            let s = vdupq_n_f32;
            let i = vdupq_n_u32;
            let x = max4(x, s(f32::MIN_POSITIVE));
            let bits = vreinterpretq_u32_f32(x);
            let e = vcvtq_f32_s32(vsubq_s32(
                vreinterpretq_s32_u32(vshrq_n_u32::<23>(bits)),
                vdupq_n_s32(126),
            ));
            let m = vreinterpretq_f32_u32(vorrq_u32(
                vandq_u32(bits, i(expf::MANTISSA)),
                i(expf::HALF_BITS),
            ));
            let small = vcltq_f32(m, s(expf::SQRT_HALF));
            let one_where_small =
                vreinterpretq_f32_u32(vandq_u32(small, vreinterpretq_u32_f32(s(1.0))));
            let e = vsubq_f32(e, one_where_small);
            let m = vsubq_f32(vbslq_f32(small, vaddq_f32(m, m), m), s(1.0));
            let z = vmulq_f32(m, m);
            let mut y = s(expf::LOG_P[0]);
            for c in &expf::LOG_P[1..] {
                y = vaddq_f32(vmulq_f32(y, m), s(*c));
            }
            let y = vsubq_f32(
                vaddq_f32(vmulq_f32(vmulq_f32(y, m), z), vmulq_f32(e, s(expf::LN2_LO))),
                vmulq_f32(z, s(0.5)),
            );
            vaddq_f32(vaddq_f32(m, y), vmulq_f32(e, s(expf::LN2_HI)))
        }
    }

    /// Bit l set where lane l of the four is set.
    #[inline(always)]
    fn bits4(m: uint32x4_t) -> u32 {
        const WEIGHTS: [u32; 4] = [1, 2, 4, 8];
        unsafe { vaddvq_u32(vandq_u32(m, vld1q_u32(WEIGHTS.as_ptr()))) }
    }

    impl Lanes for Neon {
        type Mask = Mask;

        #[inline(always)]
        fn splat(v: f32) -> Self {
            unsafe { Neon(vdupq_n_f32(v), vdupq_n_f32(v)) }
        }
        #[inline(always)]
        fn load(s: &[f32]) -> Self {
            assert!(s.len() >= LANES);
            unsafe { Neon(vld1q_f32(s.as_ptr()), vld1q_f32(s.as_ptr().add(4))) }
        }
        #[inline(always)]
        fn store(self, s: &mut [f32]) {
            assert!(s.len() >= LANES);
            unsafe {
                vst1q_f32(s.as_mut_ptr(), self.0);
                vst1q_f32(s.as_mut_ptr().add(4), self.1);
            }
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            self.zip(o, |a, b| unsafe { vaddq_f32(a, b) })
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            self.zip(o, |a, b| unsafe { vsubq_f32(a, b) })
        }
        #[inline(always)]
        fn mul(self, o: Self) -> Self {
            self.zip(o, |a, b| unsafe { vmulq_f32(a, b) })
        }
        #[inline(always)]
        fn div(self, o: Self) -> Self {
            self.zip(o, |a, b| unsafe { vdivq_f32(a, b) })
        }
        #[inline(always)]
        fn min(self, o: Self) -> Self {
            self.zip(o, min4)
        }
        #[inline(always)]
        fn max(self, o: Self) -> Self {
            self.zip(o, max4)
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            unsafe { Neon(vsqrtq_f32(self.0), vsqrtq_f32(self.1)) }
        }
        #[inline(always)]
        fn lt(self, o: Self) -> Mask {
            self.test(o, |a, b| unsafe { vcltq_f32(a, b) })
        }
        #[inline(always)]
        fn le(self, o: Self) -> Mask {
            self.test(o, |a, b| unsafe { vcleq_f32(a, b) })
        }
        #[inline(always)]
        fn gt(self, o: Self) -> Mask {
            self.test(o, |a, b| unsafe { vcgtq_f32(a, b) })
        }
        #[inline(always)]
        fn below(j: u32, end: &[u32]) -> Mask {
            assert!(end.len() >= LANES);
            unsafe {
                let j = vdupq_n_u32(j);
                Mask(
                    vcgtq_u32(vld1q_u32(end.as_ptr()), j),
                    vcgtq_u32(vld1q_u32(end.as_ptr().add(4)), j),
                )
            }
        }
        #[inline(always)]
        fn and(a: Mask, b: Mask) -> Mask {
            unsafe { Mask(vandq_u32(a.0, b.0), vandq_u32(a.1, b.1)) }
        }
        #[inline(always)]
        fn and_not(a: Mask, b: Mask) -> Mask {
            unsafe { Mask(vbicq_u32(a.0, b.0), vbicq_u32(a.1, b.1)) }
        }
        #[inline(always)]
        fn bits(m: Mask) -> u32 {
            bits4(m.0) | (bits4(m.1) << 4)
        }
        #[inline(always)]
        fn select(m: Mask, a: Self, b: Self) -> Self {
            unsafe { Neon(vbslq_f32(m.0, a.0, b.0), vbslq_f32(m.1, a.1, b.1)) }
        }
        #[inline(always)]
        fn set_where(m: Mask, v: u32, out: &mut [u32]) {
            assert!(out.len() >= LANES);
            unsafe {
                let (p, new) = (out.as_mut_ptr(), vdupq_n_u32(v));
                vst1q_u32(p, vbslq_u32(m.0, new, vld1q_u32(p)));
                vst1q_u32(p.add(4), vbslq_u32(m.1, new, vld1q_u32(p.add(4))));
            }
        }
        #[inline(always)]
        fn exp(self) -> Self {
            Neon(
                exp4(self.0, expf::HIGH, &expf::P_FALLOFF),
                exp4(self.1, expf::HIGH, &expf::P_FALLOFF),
            )
        }
        #[inline(always)]
        fn exp_wide(self) -> Self {
            Neon(
                exp4(self.0, expf::WIDE_HIGH, &expf::P),
                exp4(self.1, expf::WIDE_HIGH, &expf::P),
            )
        }
        #[inline(always)]
        fn ln(self) -> Self {
            Neon(ln4(self.0), ln4(self.1))
        }
        #[inline(always)]
        fn hsum(self) -> f32 {
            unsafe {
                // [v0+v4, v1+v5, v2+v6, v3+v7], then (s0 + s2) + (s1 + s3).
                let s = vaddq_f32(self.0, self.1);
                let pair = vadd_f32(vget_low_f32(s), vget_high_f32(s));
                vget_lane_f32::<0>(pair) + vget_lane_f32::<1>(pair)
            }
        }
        #[inline(always)]
        fn axpy(out: &mut [f32], w: f32, f: &[f32]) {
            let n = out.len().min(f.len());
            let mut i = 0;
            unsafe {
                let wv = vdupq_n_f32(w);
                while i + 4 <= n {
                    let o = out.as_mut_ptr().add(i);
                    let v = vmulq_f32(wv, vld1q_f32(f.as_ptr().add(i)));
                    vst1q_f32(o, vaddq_f32(vld1q_f32(o), v));
                    i += 4;
                }
            }
            for (o, v) in out[i..n].iter_mut().zip(&f[i..n]) {
                *o += w * v;
            }
        }
        #[inline(always)]
        fn dot(a: &[f32], b: &[f32]) -> f32 {
            let n = a.len().min(b.len());
            let mut i = 0;
            let mut acc = Neon::splat(0.0);
            while i + LANES <= n {
                acc = acc.add(Neon::load(&a[i..]).mul(Neon::load(&b[i..])));
                i += LANES;
            }
            let tail = a[i..n]
                .iter()
                .zip(&b[i..n])
                .fold(0.0, |s, (x, y)| s + x * y);
            acc.hsum() + tail
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// The polynomial exp against the library's, over the falloff's range.
    #[test]
    fn exp_is_accurate_where_gaussians_are_evaluated() {
        let mut worst: f64 = 0.0;
        for i in 0..=20_000 {
            // The argument as the engine holds it, so that only exp's own error is measured.
            let x = f64::from((-7.0 * i as f64 / 20_000.0) as Real);
            let got = Portable::splat(x as Real).exp().0[0] as f64;
            worst = worst.max((got - x.exp()).abs() / x.exp());
        }
        // Measured: 1.75e-7 (the falloff's shorter polynomial, `expf::P_FALLOFF`).
        let ulps = if cfg!(feature = "f64") { 1e-15 } else { 2e-7 };
        assert!(worst < ulps, "relative error {worst}");
    }

    /// The wide exponential and the logarithm against the library's, over the ranges the
    /// projection evaluates them on (opacity logits and log-scales; opacity over the alpha
    /// cut-off).
    #[test]
    fn exp_wide_and_ln_are_accurate() {
        let (mut worst_exp, mut worst_ln): (f64, f64) = (0.0, 0.0);
        for i in 0..=40_000 {
            let x = f64::from((-80.0 + 160.0 * i as f64 / 40_000.0) as Real);
            let got = Portable::splat(x as Real).exp_wide().0[0] as f64;
            worst_exp = worst_exp.max((got - x.exp()).abs() / x.exp());
            // Positive values from 1e-30 to 1e6, evenly in the exponent.
            let y = f64::from((10f64).powf(-30.0 + 36.0 * i as f64 / 40_000.0) as Real);
            let got = Portable::splat(y as Real).ln().0[0] as f64;
            worst_ln = worst_ln.max((got - y.ln()).abs() / y.ln().abs().max(1.0));
        }
        // Measured: 7.6e-8 and 7.5e-8 (an f32's unit in the last place is 6e-8 to 1.2e-7).
        let ulps = if cfg!(feature = "f64") { 1e-15 } else { 1.5e-7 };
        assert!(worst_exp < ulps, "exp_wide: relative error {worst_exp}");
        assert!(worst_ln < ulps, "ln: error {worst_ln}");
        // Where ln clamps: zero, negatives and NaN are the smallest normal number's.
        let floor = Portable::splat(Real::MIN_POSITIVE).ln().0[0];
        for v in [0.0, -1.0, Real::NAN] {
            assert_eq!(Portable::splat(v).ln().0[0], floor, "ln({v})");
        }
    }

    /// Random lanes through every operation, the AVX2 implementation against the portable one,
    /// bit for bit (where the CPU has AVX2).
    #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
    #[test]
    fn avx2_gives_the_portable_bits() {
        if !avx2_available() {
            eprintln!("no AVX2 here: only the portable implementation runs");
            return;
        }
        // SAFETY: the CPU has AVX2 (checked above).
        unsafe { compare_avx2() }
    }

    #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
    #[target_feature(enable = "avx2")]
    unsafe fn compare_avx2() {
        compare::<Avx2>()
    }

    /// The same for AVX-512 (where the CPU has it).
    #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
    #[test]
    fn avx512_gives_the_portable_bits() {
        if !avx512_available() {
            eprintln!("no AVX-512 here: it is not compared");
            return;
        }
        // SAFETY: the CPU has AVX2, AVX-512F and VL (checked above).
        unsafe { compare_avx512() }
    }

    #[cfg(all(target_arch = "x86_64", not(feature = "f64")))]
    #[target_feature(enable = "avx2,avx512f,avx512vl")]
    unsafe fn compare_avx512() {
        compare::<Avx512>()
    }

    /// The same for NEON (every aarch64 CPU has it).
    #[cfg(all(target_arch = "aarch64", not(feature = "f64")))]
    #[test]
    fn neon_gives_the_portable_bits() {
        compare::<Neon>()
    }

    /// Random lanes through every operation of `L`, against the portable implementation.
    #[cfg(not(feature = "f64"))]
    #[allow(dead_code)] // on a CPU family with no vector implementation
    #[inline(always)]
    fn compare<L: Lanes>() {
        fn same<L: Lanes>(a: L, b: Portable, what: &str) {
            let mut x = [0.0; LANES];
            a.store(&mut x);
            assert_eq!(x.map(f32::to_bits), b.0.map(f32::to_bits), "{what}");
        }
        let mut rng = Rng::new(11);
        for round in 0..2000 {
            let mut draw = || -> [f32; LANES] {
                std::array::from_fn(|_| match round % 5 {
                    0 => rng.uniform(-8.0, 0.5) as f32,
                    1 => rng.uniform(-1e3, 1e3) as f32,
                    2 => (rng.uniform(-1.0, 1.0) * 1e-3) as f32,
                    // Ties, signed zeros and NaN, where minimum and clamps could differ.
                    3 => [0.0, -0.0, 1.0, f32::NAN, -100.0, 0.5][rng.below(6)],
                    _ => rng.normal() as f32,
                })
            };
            let (xa, xb) = (draw(), draw());
            let (a, b) = (L::load(&xa), L::load(&xb));
            let (pa, pb) = (Portable(xa), Portable(xb));
            same(a.add(b), pa.add(pb), "add");
            same(a.sub(b), pa.sub(pb), "sub");
            same(a.mul(b), pa.mul(pb), "mul");
            same(a.div(b), pa.div(pb), "div");
            same(a.min(b), pa.min(pb), "min");
            same(a.max(b), pa.max(pb), "max");
            same(a.sqrt(), pa.sqrt(), "sqrt");
            same(a.exp(), pa.exp(), "exp");
            same(a.exp_wide(), pa.exp_wide(), "exp_wide");
            same(a.ln(), pa.ln(), "ln");
            // Rounding to indices: lanes in [0, 2^24].
            let (ia, ipa) = {
                let v = xa.map(|x| match x {
                    x if x > 0.0 => x.min(16_777_216.0),
                    x if x < 0.0 => -x * 1e4,
                    _ => 0.0,
                });
                (L::load(&v), Portable(v))
            };
            same(ia.trunc(), ipa.trunc(), "trunc");
            assert_eq!(ia.trunc().to_u32(), ipa.trunc().to_u32(), "to_u32");
            // Rows of every width a Gaussian's arrays have, and a few more; all columns or some.
            let stride: usize = [1, 2, 3, 4, 5, 8, 9, 12, 27, 48][round % 10];
            let width = [stride, stride.div_ceil(2)][round / 10 % 2];
            let rows: Vec<f32> = (0..LANES * stride)
                .map(|i| i as f32 * 0.37 - 20.5)
                .collect();
            let mut got = vec![L::splat(0.0); width];
            let mut want = vec![Portable::splat(0.0); width];
            L::load_columns(&rows, stride, &mut got);
            Portable::load_columns(&rows, stride, &mut want);
            for (c, (g, w)) in got.into_iter().zip(want).enumerate() {
                assert_eq!(w.0[3], rows[3 * stride + c], "the portable columns");
                same(g, w, "load_columns");
            }
            assert_eq!(a.hsum().to_bits(), pa.hsum().to_bits(), "hsum");
            let vs: [[f32; LANES]; 8] = std::array::from_fn(|_| draw());
            let sums = L::hsum8(vs.map(|x| L::load(&x)));
            let one_by_one = vs.map(|x| Portable(x).hsum());
            assert_eq!(
                sums.map(f32::to_bits),
                one_by_one.map(f32::to_bits),
                "hsum8"
            );
            for (m, pm) in [
                (a.lt(b), pa.lt(pb)),
                (a.le(b), pa.le(pb)),
                (a.gt(b), pa.gt(pb)),
            ] {
                assert_eq!(L::bits(m), Portable::bits(pm), "compare");
                same(L::select(m, a, b), Portable::select(pm, pa, pb), "select");
                let (m2, pm2) = (a.lt(L::splat(0.0)), pa.lt(Portable::splat(0.0)));
                assert_eq!(
                    L::bits(L::and_not(m, m2)),
                    Portable::bits(Portable::and_not(pm, pm2))
                );
                assert_eq!(
                    L::bits(L::and(m, m2)),
                    Portable::bits(Portable::and(pm, pm2))
                );
                let mut ua: [u32; LANES] = std::array::from_fn(|l| l as u32 * 3);
                let mut up = ua;
                L::set_where(m, 77, &mut ua);
                Portable::set_where(pm, 77, &mut up);
                assert_eq!(ua, up, "set_where");
                let (mut fa, mut fp) = (xb, xb);
                a.store_where(m, b, &mut fa);
                pa.store_where(pm, pb, &mut fp);
                assert_eq!(fa.map(f32::to_bits), fp.map(f32::to_bits), "store_where");
                assert_eq!(
                    L::bits(L::below(9, &ua)),
                    Portable::bits(Portable::below(9, &up))
                );
            }
            let n = round % 37;
            let va: Vec<f32> = (0..n).map(|_| rng.normal() as f32).collect();
            let vb: Vec<f32> = (0..n).map(|_| rng.normal() as f32).collect();
            assert_eq!(
                L::dot(&va, &vb).to_bits(),
                Portable::dot(&va, &vb).to_bits()
            );
            let (mut oa, mut op) = (vb.clone(), vb.clone());
            L::axpy(&mut oa, xa[0], &va);
            Portable::axpy(&mut op, xa[0], &va);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&oa), bits(&op), "axpy");
            // The fused pass against the two it stands for, each on the portable lanes.
            let vf: Vec<f32> = (0..n).map(|_| rng.normal() as f32).collect();
            let mut of = vb.clone();
            let (parts, tail) = L::axpy_dot::<false>(&mut of, xa[1], &va, &vf);
            let d = parts.hsum() + tail;
            let mut op = vb.clone();
            Portable::axpy(&mut op, xa[1], &va);
            assert_eq!(bits(&of), bits(&op), "axpy_dot's axpy");
            assert_eq!(
                d.to_bits(),
                Portable::dot(&va, &vf).to_bits(),
                "axpy_dot's dot"
            );
            // Into a slice of garbage taken as zeros, against zeros.
            let mut of = vf.clone();
            let (fresh_parts, fresh_tail) = L::axpy_dot::<true>(&mut of, xa[1], &va, &vf);
            let mut op = vec![0.0; n];
            Portable::axpy(&mut op, xa[1], &va);
            assert_eq!(bits(&of), bits(&op), "axpy_dot's fresh axpy");
            assert_eq!((fresh_parts.hsum() + fresh_tail).to_bits(), d.to_bits());
        }
    }

    /// The lane-split dot product against a plain running sum, in f64.
    #[test]
    fn dot_matches_a_plain_sum() {
        let mut rng = Rng::new(3);
        for n in [0, 1, 7, 8, 9, 63, 64, 65, 130] {
            let a: Vec<Real> = (0..n).map(|_| rng.uniform(-1.0, 1.0) as Real).collect();
            let b: Vec<Real> = (0..n).map(|_| rng.uniform(-1.0, 1.0) as Real).collect();
            let plain: f64 = a
                .iter()
                .zip(&b)
                .map(|(x, y)| f64::from(*x) * f64::from(*y))
                .sum();
            let fast = f64::from(Portable::dot(&a, &b));
            assert!(
                (fast - plain).abs() < 1e-5 * (1.0 + n as f64),
                "n={n}: {fast} vs {plain}"
            );
        }
    }
}
