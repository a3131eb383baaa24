//! Dense kernels on row-major `f32` slices: GEMM (through the `gemm` crate, the
//! backend dfdx itself uses, multithreaded on rayon's global pool), fused ELU /
//! ReLU forward and backward, column sums.
//!
//! Why not dfdx autograd: dfdx 0.13 measured with ELU composed
//! from its ops at ~4x the plain GEMM time (160 ms vs 40 ms, batch 4096); the
//! networks here are plain MLPs whose backward pass is a handful of GEMMs, so
//! the learner writes forward/backward by hand over these kernels and checks
//! them against finite differences (see `nets` tests).

use rayon::prelude::*;
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, Ordering};
use std::time::Instant;

/// Elements per rayon task for element-wise kernels.
const CHUNK: usize = 16 * 1024;

/// Which GEMM kernels [`gemm`] runs. Process-wide; `Auto` unless changed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernels {
    /// `gemm` 0.19: the widest SIMD the CPU offers, chosen at run time
    /// (AVX-512 F on CPUs that have it, else AVX2 + FMA, else SSE).
    Auto,
    /// `gemm` 0.15, the learner's first kernels: AVX2 on stable Rust even where
    /// AVX-512 exists. Kept for side-by-side benchmarks (`benches/ppo.rs`).
    Legacy,
}

static KERNELS: AtomicU8 = AtomicU8::new(0);
/// Set inside [`with_gemm_clock`]: [`gemm`] calls inside [`serial`] add their time
/// to [`SHARD_GEMM_NS`].
static GEMM_CLOCK: AtomicBool = AtomicBool::new(false);
static SHARD_GEMM_NS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    /// Set inside [`serial`]: kernels run on the calling thread only.
    static SERIAL: Cell<bool> = const { Cell::new(false) };
    /// Set inside [`with_precision`].
    static PRECISION: Cell<Precision> = const { Cell::new(Precision::F32) };
}

/// Precision of [`gemm`]'s products on the calling thread.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// f32 inputs and sums (the `gemm` crate).
    #[default]
    F32,
    /// Inputs rounded to bf16, products summed in f32, on AMX tiles
    /// ([`super::amx`]); f32 where the CPU has no AMX.
    Bf16,
    /// Inputs rounded to bf16, products summed in f32 by AVX512-BF16's
    /// `VDPBF16PS` ([`super::bf16_avx512`]: AMD Zen 4 and later, Intel Cooper
    /// Lake); f32 where the CPU lacks it, and for the narrow products where f32 is
    /// faster ([`super::bf16_avx512::pays_off`]). Config value `"bf16-avx512"`.
    #[serde(rename = "bf16-avx512")]
    Bf16Avx512,
}

/// Runs `f` with [`gemm`] at `precision` on the calling thread (the AMX kernels
/// of [`Precision::Bf16`] are single-threaded; those of
/// [`Precision::Bf16Avx512`] use rayon's pool outside [`serial`]).
pub fn with_precision<R>(precision: Precision, f: impl FnOnce() -> R) -> R {
    let was = PRECISION.with(|p| p.replace(precision));
    let out = f();
    PRECISION.with(|p| p.set(was));
    out
}

/// The precision [`Precision::Bf16`] actually gets on this machine (for logs).
pub fn bf16_backend() -> &'static str {
    precision_backend(Precision::Bf16)
}

/// The kernels `precision` actually runs on this machine (for logs): a bf16
/// precision whose instructions the CPU lacks falls back to f32, and says so.
pub fn precision_backend(precision: Precision) -> &'static str {
    match precision {
        Precision::F32 => "f32",
        Precision::Bf16 if super::amx::available() => "AMX tiles",
        Precision::Bf16 => "none (no AMX-BF16 here): f32",
        Precision::Bf16Avx512 if super::bf16_avx512::available() => "AVX512-BF16 (VDPBF16PS)",
        Precision::Bf16Avx512 => "none (no AVX512-BF16 here): f32",
    }
}

/// Whether `precision` runs its own kernels on this machine (not the f32 fallback).
pub fn precision_available(precision: Precision) -> bool {
    match precision {
        Precision::F32 => true,
        Precision::Bf16 => super::amx::available(),
        Precision::Bf16Avx512 => super::bf16_avx512::available(),
    }
}

/// Runs `f` with every kernel of this module single-threaded on the calling
/// thread: for callers that already split the work across threads (the PPO
/// update runs one shard of each mini-batch per thread).
pub fn serial<R>(f: impl FnOnce() -> R) -> R {
    let was = SERIAL.with(|s| s.replace(true));
    let out = f();
    SERIAL.with(|s| s.set(was));
    out
}

/// Runs `f` with [`gemm`]'s clock on: every call made inside [`serial`] (the PPO
/// update's per-thread shards), on any thread, adds its time to a process-wide
/// sum read by [`take_shard_gemm_s`] (`rall bench scaling`). Off otherwise: the
/// clock costs one relaxed load per call.
pub fn with_gemm_clock<R>(f: impl FnOnce() -> R) -> R {
    let was = GEMM_CLOCK.swap(true, Ordering::Relaxed);
    let out = f();
    GEMM_CLOCK.store(was, Ordering::Relaxed);
    out
}

/// Seconds of [`gemm`] inside [`serial`] under [`with_gemm_clock`] since the last
/// call, summed over threads; resets the sum.
pub fn take_shard_gemm_s() -> f64 {
    SHARD_GEMM_NS.swap(0, Ordering::Relaxed) as f64 * 1e-9
}

/// Whether the calling thread is inside [`serial`].
pub fn is_serial() -> bool {
    SERIAL.with(|s| s.get())
}

/// `f` over `CHUNK`-sized pieces of `x`, in parallel unless [`is_serial`].
fn for_chunks(x: &mut [f32], f: impl Fn(&mut [f32]) + Sync + Send) {
    if is_serial() {
        x.chunks_mut(CHUNK).for_each(f);
    } else {
        x.par_chunks_mut(CHUNK).for_each(f);
    }
}

/// `f` over matching `CHUNK`-sized pieces of `x` and `y`, in parallel unless [`is_serial`].
fn for_chunk_pairs(x: &mut [f32], y: &[f32], f: impl Fn(&mut [f32], &[f32]) + Sync + Send) {
    if is_serial() {
        x.chunks_mut(CHUNK)
            .zip(y.chunks(CHUNK))
            .for_each(|(x, y)| f(x, y));
    } else {
        x.par_chunks_mut(CHUNK)
            .zip(y.par_chunks(CHUNK))
            .for_each(|(x, y)| f(x, y));
    }
}

/// Selects the GEMM kernels for the whole process (benchmarks compare both).
pub fn set_kernels(k: Kernels) {
    KERNELS.store(k as u8, Ordering::Relaxed);
}

/// The GEMM kernels in use.
pub fn kernels() -> Kernels {
    match KERNELS.load(Ordering::Relaxed) {
        0 => Kernels::Auto,
        _ => Kernels::Legacy,
    }
}

/// The instruction set [`Kernels::Auto`] runs on this CPU (for logs).
pub fn simd_level() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            return "avx512f";
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            return "avx2+fma";
        }
        "sse2"
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        "native"
    }
}

/// Runs `f` compiled for the widest SIMD level the CPU offers (AVX-512, AVX2,
/// else baseline), chosen at run time. `f` must be a plain loop (it is inlined
/// into the feature-enabled frame, so LLVM vectorises it for that level).
#[inline(always)]
pub fn with_simd<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    {
        if let Some(v4) = pulp::x86::V4::try_new() {
            return v4.vectorize(f);
        }
        if let Some(v3) = pulp::x86::V3::try_new() {
            return v3.vectorize(f);
        }
    }
    f()
}

/// Panics unless `a`, `b` and `c` hold at least `m x k`, `k x n` and `m x n`
/// values, the products computed with overflow checks (a wrapped product would
/// let the unchecked kernels reach past the slices).
pub(crate) fn assert_gemm_dims(m: usize, n: usize, k: usize, a: usize, b: usize, c: usize) {
    let size = |x: usize, y: usize| {
        x.checked_mul(y)
            .filter(|&s| s <= isize::MAX as usize / 4)
            .unwrap_or_else(|| panic!("gemm: a {x} x {y} matrix is larger than memory"))
    };
    assert!(
        a >= size(m, k) && b >= size(k, n) && c >= size(m, n),
        "gemm: slices of {a}, {b}, {c} values for {m} x {k} times {k} x {n}"
    );
}

/// `c[m x n] = (accumulate ? c : 0) + op(a)[m x k] * op(b)[k x n]`, all row-major.
/// `a_t`: `a` is stored as `k x m` (use its transpose); `b_t`: `b` is stored as `n x k`.
/// Runs the kernels of the calling thread's [`Precision`] (f32 where the CPU lacks
/// that precision's instructions).
#[allow(clippy::too_many_arguments)]
pub fn gemm(
    m: usize,
    n: usize,
    k: usize,
    a: &[f32],
    a_t: bool,
    b: &[f32],
    b_t: bool,
    c: &mut [f32],
    accumulate: bool,
) {
    let clock = (GEMM_CLOCK.load(Ordering::Relaxed) && is_serial()).then(Instant::now);
    gemm_at_precision(m, n, k, a, a_t, b, b_t, c, accumulate);
    if let Some(t0) = clock {
        SHARD_GEMM_NS.fetch_add(t0.elapsed().as_nanos() as u64, Ordering::Relaxed);
    }
}

/// [`gemm`] without its clock.
#[allow(clippy::too_many_arguments)]
#[allow(unsafe_code)]
fn gemm_at_precision(
    m: usize,
    n: usize,
    k: usize,
    a: &[f32],
    a_t: bool,
    b: &[f32],
    b_t: bool,
    c: &mut [f32],
    accumulate: bool,
) {
    assert_gemm_dims(m, n, k, a.len(), b.len(), c.len());
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            c[..m * n].fill(0.0);
        }
        return;
    }
    #[cfg(target_arch = "x86_64")]
    match PRECISION.with(|p| p.get()) {
        Precision::Bf16 if super::amx::available() => {
            return super::amx::gemm_bf16(m, n, k, a, a_t, b, b_t, c, accumulate);
        }
        Precision::Bf16Avx512
            if super::bf16_avx512::available() && super::bf16_avx512::pays_off(n, k) =>
        {
            return super::bf16_avx512::gemm_bf16(m, n, k, a, a_t, b, b_t, c, accumulate);
        }
        _ => {}
    }
    let (a_rs, a_cs) = if a_t {
        (1, m as isize)
    } else {
        (k as isize, 1)
    };
    let (b_rs, b_cs) = if b_t {
        (1, k as isize)
    } else {
        (n as isize, 1)
    };
    let (c, a, b) = (c.as_mut_ptr(), a.as_ptr(), b.as_ptr());
    let n_rs = n as isize;
    let serial = is_serial();
    // SAFETY: the asserts above bound every index the strides can reach:
    // a: max (m-1)*a_rs + (k-1)*a_cs < m*k, same for b and c; `c` is exclusive.
    // Both crates take the same arguments (dst, its column/row strides, read_dst,
    // lhs, rhs, alpha, beta, conjugations, parallelism).
    // One call shape for both crates: `c = 1 * c (if accumulate) + 1 * a b`, no
    // conjugation, single-threaded inside `serial`.
    macro_rules! call {
        ($krate:ident) => {
            $krate::gemm(
                m,
                n,
                k,
                c,
                1,
                n_rs,
                accumulate,
                a,
                a_cs,
                a_rs,
                b,
                b_cs,
                b_rs,
                1.0,
                1.0,
                false,
                false,
                false,
                if serial {
                    $krate::Parallelism::None
                } else {
                    $krate::Parallelism::Rayon(0)
                },
            )
        };
    }
    unsafe {
        match kernels() {
            Kernels::Auto => call!(gemm),
            Kernels::Legacy => call!(gemm_legacy),
        }
    }
}

/// `exp(x)` for `x <= 0` (inputs are clamped to `[-87, 0]`), relative error
/// about `1e-7 (1 + |x|)` (f32 argument reduction), branch-free so the loops below vectorise on baseline x86-64.
#[inline(always)]
pub fn exp_nonpos(x: f32) -> f32 {
    let x = x.clamp(-87.0, 0.0);
    let t = x * std::f32::consts::LOG2_E;
    // round to nearest with the 1.5*2^23 trick (no SSE4.1 `round` needed): the
    // low mantissa bits of `r` hold n (two's complement), -126 <= n <= 0
    let r = t + 12_582_912.0;
    let n = r - 12_582_912.0;
    let y = (t - n) * std::f32::consts::LN_2; // |y| <= ln2/2
    let p = 1.0
        + y * (1.0
            + y * (0.5
                + y * (1.0 / 6.0 + y * (1.0 / 24.0 + y * (1.0 / 120.0 + y * (1.0 / 720.0))))));
    // 2^n built from those bits with integer lane operations (a float-to-int
    // cast here kept the loops from vectorising): shifting by 23 drops every bit
    // of r above its low 9, leaving the biased exponent n + 127 in place
    let scale = f32::from_bits(r.to_bits().wrapping_add(127) << 23);
    p * scale
}

/// In place `x <- elu(x) = x if x > 0 else exp(x) - 1`.
pub fn elu_inplace(x: &mut [f32]) {
    for_chunks(x, |c| {
        with_simd(
            #[inline(always)]
            || {
                for v in c {
                    let z = *v;
                    let e = exp_nonpos(z) - 1.0;
                    *v = if z > 0.0 { z } else { e };
                }
            },
        )
    });
}

/// Backward of ELU written in terms of its output `a`: `g <- g * (a > 0 ? 1 : a + 1)`.
pub fn elu_backward_inplace(g: &mut [f32], a: &[f32]) {
    for_chunk_pairs(g, a, |g, a| {
        with_simd(
            #[inline(always)]
            || {
                for (g, &a) in g.iter_mut().zip(a) {
                    *g *= if a > 0.0 { 1.0 } else { a + 1.0 };
                }
            },
        )
    });
}

/// `acc += x`, element-wise (summing per-thread gradients).
pub fn add_assign(acc: &mut [f32], x: &[f32]) {
    for_chunk_pairs(acc, x, |acc, x| {
        with_simd(
            #[inline(always)]
            || {
                for (a, &x) in acc.iter_mut().zip(x) {
                    *a += x;
                }
            },
        )
    });
}

/// In place ReLU.
pub fn relu_inplace(x: &mut [f32]) {
    with_simd(
        #[inline(always)]
        || {
            for v in x {
                *v = v.max(0.0);
            }
        },
    )
}

/// `y[r, :] = bias` for every row (`y` is `rows x bias.len()`).
pub fn fill_rows(y: &mut [f32], bias: &[f32]) {
    for row in y.chunks_exact_mut(bias.len()) {
        row.copy_from_slice(bias);
    }
}

/// `out[j] += sum_r x[r, j]` for `x` of `rows x out.len()`.
pub fn add_col_sums(x: &[f32], out: &mut [f32]) {
    with_simd(
        #[inline(always)]
        || {
            for row in x.chunks_exact(out.len()) {
                for (o, v) in out.iter_mut().zip(row) {
                    *o += v;
                }
            }
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_exp_is_accurate() {
        let mut x = -80.0f32;
        while x <= 0.0 {
            let (a, b) = (exp_nonpos(x), x.exp());
            assert!(
                (a - b).abs() <= 2e-7 * (1.0 - x) * b + 1e-30,
                "x={x} {a} {b}"
            );
            x += 0.013;
        }
        assert_eq!(exp_nonpos(0.0), 1.0);
        // the same bits as building 2^n from a cast of n (the first version)
        let by_cast = |x: f32| {
            let t = x.clamp(-87.0, 0.0) * std::f32::consts::LOG2_E;
            let n = (t + 12_582_912.0) - 12_582_912.0;
            let y = (t - n) * std::f32::consts::LN_2;
            let p = 1.0
                + y * (1.0
                    + y * (0.5
                        + y * (1.0 / 6.0
                            + y * (1.0 / 24.0 + y * (1.0 / 120.0 + y * (1.0 / 720.0))))));
            p * f32::from_bits((((n as i32) + 127) << 23) as u32)
        };
        let mut x = -90.0f32;
        while x <= 1.0 {
            assert_eq!(exp_nonpos(x).to_bits(), by_cast(x).to_bits(), "x={x}");
            x += 0.000_37;
        }
        assert!(exp_nonpos(-1e9) >= 0.0);
    }

    #[test]
    fn gemm_transposes_match_naive() {
        let (m, n, k) = (5, 7, 3);
        let a: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i as f32 * 0.11).cos()).collect();
        let naive = |a_at: &dyn Fn(usize, usize) -> f32, b_at: &dyn Fn(usize, usize) -> f32| {
            let mut c = vec![0.0; m * n];
            for i in 0..m {
                for j in 0..n {
                    c[i * n + j] = (0..k).map(|p| a_at(i, p) * b_at(p, j)).sum();
                }
            }
            c
        };
        let want = naive(&|i, p| a[i * k + p], &|p, j| b[p * n + j]);
        let mut c = vec![1.0; m * n];
        gemm(m, n, k, &a, false, &b, false, &mut c, false);
        for (x, y) in c.iter().zip(&want) {
            assert!((x - y).abs() < 1e-5);
        }
        // transposed storage of both operands, accumulating
        let at: Vec<f32> = (0..k * m).map(|i| a[(i % m) * k + i / m]).collect();
        let bt: Vec<f32> = (0..n * k).map(|i| b[(i % k) * n + i / k]).collect();
        gemm(m, n, k, &at, true, &bt, true, &mut c, true);
        for (x, y) in c.iter().zip(&want) {
            assert!((x - 2.0 * y).abs() < 1e-5);
        }
    }
}
