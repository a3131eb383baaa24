//! Matrix products with inputs rounded to bf16 and products summed in f32 on
//! AVX512-BF16 (`VDPBF16PS`: 16 lanes, each adding two bf16 products to an f32
//! sum), for CPUs that have it without AMX tiles (AMD Zen 4 and later, Intel
//! Cooper Lake). One `VDPBF16PS` on 512 bits does 32 multiply-adds, twice an f32
//! `VFMADD` of the same width. The f32 master weights and Adam are untouched:
//! only the operands of each product are rounded.
//!
//! [`gemm_bf16`] has [`super::mat::gemm`]'s contract, every transposition included
//! (the learner uses `x W` forward, `dY W^T` for dX and `X^T dY` for dW).
//!
//! Design (BLIS-style, for the learner's shapes: 768- or 1,536-row shards, layers of
//! 48-512, K from 12 to 1,536):
//! - K is cut into blocks of at most [`KC_MAX`] values; each block is packed once,
//!   rounded to bf16 (round to nearest even, `VCVTNE2PS2BF16`), as *pairs along K*:
//!   one 32-bit word holds `(x[kk], x[kk + 1])`, the operand layout `VDPBF16PS` reads.
//! - `op(a)` is packed into panels of [`MR`] rows (`[pair][row]`), `op(b)` into panels
//!   of [`NR`] columns (`[pair][column]`), both zero-padded (an odd K's last pair, the
//!   rows and columns past the edge), so the microkernel never branches on edges.
//! - The microkernel keeps a 6 x 64 block of `c` in 24 zmm f32 accumulators; per pair
//!   of K it loads 4 vectors of `b`, broadcasts 6 words of `a`, and issues 24
//!   `VDPBF16PS`. Edges of `c` are read and written with lane masks.
//! - Loop order per K block: pack `op(b)` (all columns), then per block of [`MC`] rows
//!   pack `op(a)` and sweep the column panels, the row panels inside, so a `b` panel
//!   (`KC_MAX / 2 x 64` words, 24 KiB) stays in L1 while the `a` block streams from L2.
//!   Outside [`super::mat::serial`] the row blocks run on rayon's pool.
//!
//! `unsafe` here is the vector intrinsics' (raw loads and stores, and calling
//! functions compiled for AVX512-BF16 once [`available`] said the CPU has it).

use std::cell::RefCell;
use std::sync::OnceLock;

use rayon::prelude::*;

/// Rows of `c` per microkernel call.
pub const MR: usize = 6;
/// Columns of `c` per microkernel call (4 zmm of 16 f32).
pub const NR: usize = 64;
/// f32 lanes of a zmm register.
const LANES: usize = 16;
/// K values per packed block (even: blocks hold whole pairs).
pub const KC_MAX: usize = 192;
/// Rows of `op(a)` per packed block, and per rayon task (a multiple of [`MR`]).
pub const MC: usize = 96;

/// Whether this CPU runs AVX512-BF16 (with AVX-512 F and BW, which the packing
/// uses). Asked once.
pub fn available() -> bool {
    static AVAILABLE: OnceLock<bool> = OnceLock::new();
    *AVAILABLE.get_or_init(detect)
}

/// Whether a product of this shape runs faster in bf16 than in f32. An output
/// narrower than half a panel fills too few of the 64 columns a micro-tile computes,
/// and a K shorter than 32 packs more than it multiplies: the learner's action
/// layer (768 x 12 x 128) took three times as long in bf16 as in f32 (`cargo bench
/// --bench ppo`), so [`super::mat::gemm`] runs such products in f32.
pub fn pays_off(n: usize, k: usize) -> bool {
    n >= NR / 2 && k >= 32
}

#[cfg(target_arch = "x86_64")]
fn detect() -> bool {
    std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512bw")
        && std::arch::is_x86_feature_detected!("avx512bf16")
}

#[cfg(not(target_arch = "x86_64"))]
fn detect() -> bool {
    false
}

/// One GEMM the learner runs: `op(a)[m x k] op(b)[k x n]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GemmShape {
    pub m: usize,
    pub n: usize,
    pub k: usize,
    pub a_t: bool,
    pub b_t: bool,
    /// What it computes, for tables.
    pub what: &'static str,
}

/// The distinct GEMMs of one mini-batch shard of `rows` samples through the
/// learner's networks at the defaults (actor `obs -> 512 -> 256 -> 128 -> act`,
/// IQN critic trunk `obs -> 512 -> 256 -> 128`, 64 quantile fractions embedded from
/// 64 cosines into the 128-wide merge), in the transpositions `nets` uses:
/// forward `x W`, dX = `dY W^T`, dW = `X^T dY` (the first layer has no dX).
pub fn learner_shapes(rows: usize, obs: usize, act: usize) -> Vec<GemmShape> {
    let s = |m, n, k, a_t, b_t, what| GemmShape {
        m,
        n,
        k,
        a_t,
        b_t,
        what,
    };
    let (taus, cos, feat) = (64, 64, 128);
    vec![
        s(rows, 512, obs, false, false, "forward obs -> 512"),
        s(rows, 256, 512, false, false, "forward 512 -> 256"),
        s(rows, 128, 256, false, false, "forward 256 -> 128"),
        s(rows, act, 128, false, false, "forward 128 -> act"),
        s(rows, 512, 256, false, true, "dX 256 -> 512"),
        s(rows, 256, 128, false, true, "dX 128 -> 256"),
        s(rows, 128, act, false, true, "dX act -> 128"),
        s(obs, 512, rows, true, false, "dW obs x 512"),
        s(512, 256, rows, true, false, "dW 512 x 256"),
        s(256, 128, rows, true, false, "dW 256 x 128"),
        s(128, act, rows, true, false, "dW 128 x act"),
        s(taus, feat, cos, false, false, "IQN embedding forward"),
        s(cos, feat, taus, true, false, "IQN embedding dW"),
        s(rows, taus, feat, false, true, "IQN quantiles Z = phi g^T"),
        s(rows, feat, taus, false, false, "IQN dphi = dZ g"),
        s(taus, feat, rows, true, false, "IQN dg = dZ^T phi"),
    ]
}

/// Packed operands, reused between calls on a thread (`a` and `b` apart: a
/// rayon task on the calling thread packs `a` while the caller holds `b`).
#[derive(Default)]
struct Pack {
    words: Vec<u32>,
    /// One vector's pairs before they are spread into a panel.
    tmp: Vec<u32>,
}

thread_local! {
    static PACK_A: RefCell<Pack> = RefCell::new(Pack::default());
    static PACK_B: RefCell<Pack> = RefCell::new(Pack::default());
}

/// How one operand lies in memory, seen as `count` vectors (rows of `op(a)` or
/// columns of `op(b)`) of `k` values: value `kk` of vector `v` is at
/// `src[v * ld + kk]` if `k_contiguous`, else at `src[kk * ld + v]`.
#[derive(Clone, Copy)]
struct Operand<'s> {
    src: &'s [f32],
    ld: usize,
    k_contiguous: bool,
}

/// Packs vectors `first..first + count`, K values `k0..k0 + kc`, into panels of
/// `width` vectors: word `p * width + v % width` of panel `v / width` holds the
/// bf16 pair `(k0 + 2p, k0 + 2p + 1)` of vector `first + v`; padding is zero.
fn pack_panels(
    op: Operand,
    first: usize,
    count: usize,
    k0: usize,
    kc: usize,
    width: usize,
    pack: &mut Pack,
) {
    let kp = kc.div_ceil(2);
    let panel = kp * width;
    pack.words.clear();
    pack.words.resize(count.div_ceil(width) * panel, 0);
    let Pack { words, tmp } = pack;
    if op.k_contiguous {
        tmp.resize(kp, 0);
        for v in 0..count {
            let start = (first + v) * op.ld + k0;
            bf16_pairs(&op.src[start..start + kc], tmp);
            let base = (v / width) * panel + v % width;
            for (p, &w) in tmp.iter().enumerate() {
                words[base + p * width] = w;
            }
        }
    } else {
        tmp.resize(count, 0);
        for p in 0..kp {
            let kk = k0 + 2 * p;
            let lo = &op.src[kk * op.ld + first..kk * op.ld + first + count];
            let hi = (2 * p + 1 < kc)
                .then(|| &op.src[(kk + 1) * op.ld + first..(kk + 1) * op.ld + first + count]);
            interleave_pairs(lo, hi, tmp);
            for (q, chunk) in tmp.chunks(width).enumerate() {
                let o = q * panel + p * width;
                words[o..o + chunk.len()].copy_from_slice(chunk);
            }
        }
    }
}

/// `dst[p] = (bf16(src[2p]), bf16(src[2p + 1]))` as one word, the first in the
/// low half; an odd length's last pair has a zero high half.
fn bf16_pairs(src: &[f32], dst: &mut [u32]) {
    assert!(
        dst.len() >= src.len().div_ceil(2),
        "bf16_pairs: short output"
    );
    // SAFETY: callers reach this only after `gemm_bf16` asserted `available()`
    // (the CPU has AVX-512 F, BW and BF16); the lengths are checked above.
    #[cfg(target_arch = "x86_64")]
    #[allow(unsafe_code)]
    unsafe {
        bf16_pairs_avx512(src, dst);
    }
}

/// `dst[j] = (bf16(lo[j]), bf16(hi[j]))` as one word (high half zero without `hi`).
fn interleave_pairs(lo: &[f32], hi: Option<&[f32]>, dst: &mut [u32]) {
    assert!(
        dst.len() >= lo.len() && hi.is_none_or(|h| h.len() == lo.len()),
        "interleave_pairs: mismatched lengths"
    );
    // SAFETY: as in `bf16_pairs`: the features were checked at `gemm_bf16`'s entry,
    // the lengths above.
    #[cfg(target_arch = "x86_64")]
    #[allow(unsafe_code)]
    unsafe {
        interleave_pairs_avx512(lo, hi, dst);
    }
}

/// Lane mask of the first `n` of 16 lanes.
#[inline(always)]
fn lanes_mask(n: usize) -> u16 {
    if n >= LANES {
        u16::MAX
    } else {
        (1u16 << n) - 1
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
#[allow(unsafe_code)]
fn bf16_pairs_avx512(src: &[f32], dst: &mut [u32]) {
    use std::arch::x86_64::*;
    let n = src.len();
    let mut i = 0;
    while i < n {
        // 32 values (16 pairs) per step; the tail's missing values load as zero.
        let lo_n = (n - i).min(LANES);
        let hi_n = (n - i).saturating_sub(LANES).min(LANES);
        let words = (lo_n + hi_n).div_ceil(2);
        // SAFETY: the masked loads read lanes i..i + lo_n and i + 16..i + 16 + hi_n,
        // all < n = src.len(); the masked store writes words i / 2 .. i / 2 + words
        // with words <= (n - i).div_ceil(2), inside dst (asserted by the caller).
        unsafe {
            let lo = _mm512_maskz_loadu_ps(lanes_mask(lo_n), src.as_ptr().add(i));
            // (wrapping: past the end when hi_n is 0, and then not read)
            let hi = _mm512_maskz_loadu_ps(lanes_mask(hi_n), src.as_ptr().wrapping_add(i + LANES));
            // lower 16 bf16 from the second operand: the words come out in order
            let packed: __m512i = std::mem::transmute(_mm512_cvtne2ps_pbh(hi, lo));
            _mm512_mask_storeu_epi32(
                dst.as_mut_ptr().add(i / 2) as *mut i32,
                lanes_mask(words),
                packed,
            );
        }
        i += 2 * LANES;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
#[allow(unsafe_code)]
fn interleave_pairs_avx512(lo: &[f32], hi: Option<&[f32]>, dst: &mut [u32]) {
    use std::arch::x86_64::*;
    // bf16 lane 2j <- lo[j] (lane j of the conversion), 2j + 1 <- hi[j] (lane 16 + j)
    let order: [i16; 32] = std::array::from_fn(|l| ((l / 2) + (l % 2) * LANES) as i16);
    // SAFETY: a plain load of a 64-byte local array.
    let order = unsafe { _mm512_loadu_epi16(order.as_ptr()) };
    let n = lo.len();
    for i in (0..n).step_by(LANES) {
        let mask = lanes_mask(n - i);
        // SAFETY: the masked loads read lanes i..min(i + 16, n) of `lo` and of `hi`
        // (same length, asserted by the caller); the masked store writes the same
        // lanes of `dst`, which is at least as long.
        unsafe {
            let l = _mm512_maskz_loadu_ps(mask, lo.as_ptr().add(i));
            let h = match hi {
                Some(h) => _mm512_maskz_loadu_ps(mask, h.as_ptr().add(i)),
                None => _mm512_setzero_ps(),
            };
            let both: __m512i = std::mem::transmute(_mm512_cvtne2ps_pbh(h, l));
            let pairs = _mm512_permutexvar_epi16(order, both);
            _mm512_mask_storeu_epi32(dst.as_mut_ptr().add(i) as *mut i32, mask, pairs);
        }
    }
}

/// `c[rows x cols] (+)= a_panel b_panel` over `kp` pairs: `a` is one packed panel
/// of [`MR`] rows, `b` one of [`NR`] columns; `c` starts at the block's first
/// element, rows `ldc` apart. Reads `c` first only if `load_c`.
#[allow(clippy::too_many_arguments)]
fn micro_tile(
    kp: usize,
    a: &[u32],
    b: &[u32],
    c: &mut [f32],
    ldc: usize,
    rows: usize,
    cols: usize,
    load_c: bool,
) {
    assert!(
        a.len() >= kp * MR
            && b.len() >= kp * NR
            && (1..=MR).contains(&rows)
            && (1..=NR).contains(&cols)
            && cols <= ldc
            && (rows - 1) * ldc + cols <= c.len(),
        "micro_tile: operands shorter than the block"
    );
    // SAFETY: the features were checked at `gemm_bf16`'s entry; the lengths above.
    #[cfg(target_arch = "x86_64")]
    #[allow(unsafe_code)]
    unsafe {
        micro_tile_avx512(kp, a, b, c, ldc, rows, cols, load_c);
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
#[allow(unsafe_code, clippy::too_many_arguments)]
fn micro_tile_avx512(
    kp: usize,
    a: &[u32],
    b: &[u32],
    c: &mut [f32],
    ldc: usize,
    rows: usize,
    cols: usize,
    load_c: bool,
) {
    use std::arch::x86_64::*;
    const VECS: usize = NR / LANES;
    let masks: [u16; VECS] = std::array::from_fn(|q| lanes_mask(cols.saturating_sub(q * LANES)));
    let mut acc = [[_mm512_setzero_ps(); VECS]; MR];
    if load_c {
        for (r, acc_r) in acc.iter_mut().enumerate().take(rows) {
            for (q, v) in acc_r.iter_mut().enumerate() {
                // SAFETY: lanes j < cols of row r < rows: offset r * ldc + j <
                // (rows - 1) * ldc + cols <= c.len() (asserted by the caller);
                // masked-off lanes are not read.
                // (wrapping: a fully masked vector may start past the end)
                *v = unsafe {
                    _mm512_maskz_loadu_ps(masks[q], c.as_ptr().wrapping_add(r * ldc + q * LANES))
                };
            }
        }
    }
    let (a, b) = (a.as_ptr(), b.as_ptr());
    for p in 0..kp {
        // SAFETY: words p * NR .. p * NR + NR of b and p * MR .. p * MR + MR of a,
        // p < kp: inside the kp * NR and kp * MR words asserted by the caller.
        unsafe {
            let mut bv: [__m512bh; VECS] = std::mem::transmute([_mm512_setzero_ps(); VECS]);
            for (q, v) in bv.iter_mut().enumerate() {
                *v = std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_epi32(
                    b.add(p * NR + q * LANES) as *const i32,
                ));
            }
            for (r, acc_r) in acc.iter_mut().enumerate() {
                let av: __m512bh =
                    std::mem::transmute(_mm512_set1_epi32(*a.add(p * MR + r) as i32));
                for (v, &bq) in acc_r.iter_mut().zip(&bv) {
                    *v = _mm512_dpbf16_ps(*v, av, bq);
                }
            }
        }
    }
    for (r, acc_r) in acc.iter().enumerate().take(rows) {
        for (q, &v) in acc_r.iter().enumerate() {
            // SAFETY: lanes j < cols of row r < rows, inside c as for the loads above
            // (c is exclusive); masked-off lanes are not written.
            unsafe {
                _mm512_mask_storeu_ps(
                    c.as_mut_ptr().wrapping_add(r * ldc + q * LANES),
                    masks[q],
                    v,
                )
            };
        }
    }
}

/// K blocks of at most [`KC_MAX`] values, as even as whole pairs allow.
fn k_blocks(k: usize) -> impl Iterator<Item = (usize, usize)> {
    let blocks = k.div_ceil(KC_MAX).max(1);
    let size = k.div_ceil(blocks).next_multiple_of(2);
    (0..k).step_by(size).map(move |k0| (k0, size.min(k - k0)))
}

/// Rows `i0..i0 + rows` of `c` (given as `c_rows`, `rows x n`) over K block
/// `k0..k0 + kc`: packs that block of `op(a)` on this thread and multiplies it
/// by the packed `b` (all column panels).
#[allow(clippy::too_many_arguments)]
fn row_block(
    a: Operand,
    i0: usize,
    rows: usize,
    k0: usize,
    kc: usize,
    b_words: &[u32],
    n: usize,
    c_rows: &mut [f32],
    load_c: bool,
) {
    let kp = kc.div_ceil(2);
    PACK_A.with(|pack| {
        let pack = &mut *pack.borrow_mut();
        pack_panels(a, i0, rows, k0, kc, MR, pack);
        for (jp, b_panel) in b_words.chunks_exact(kp * NR).enumerate() {
            let j = jp * NR;
            for (ip, a_panel) in pack.words.chunks_exact(kp * MR).enumerate() {
                let i = ip * MR;
                let tile = &mut c_rows[i * n + j..];
                let (r, w) = (MR.min(rows - i), NR.min(n - j));
                micro_tile(kp, a_panel, b_panel, tile, n, r, w, load_c);
            }
        }
    });
}

/// `c[m x n] = (accumulate ? c : 0) + op(a) op(b)`, as [`super::mat::gemm`], with
/// `op(a)` and `op(b)` rounded to bf16 (nearest even; subnormal inputs read as
/// zero) and the products summed in f32 by `VDPBF16PS`. Call only when
/// [`available`]. Multithreaded over blocks of rows unless inside
/// [`super::mat::serial`].
#[allow(clippy::too_many_arguments)]
pub fn gemm_bf16(
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
    assert!(available(), "this CPU has no AVX512-BF16");
    super::mat::assert_gemm_dims(m, n, k, a.len(), b.len(), c.len());
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            c[..m * n].fill(0.0);
        }
        return;
    }
    // op(a): rows are vectors, K contiguous unless transposed; op(b): columns are
    // vectors, K contiguous only when transposed.
    let a_op = Operand {
        src: a,
        ld: if a_t { m } else { k },
        k_contiguous: !a_t,
    };
    let b_op = Operand {
        src: b,
        ld: if b_t { k } else { n },
        k_contiguous: b_t,
    };
    let parallel = !super::mat::is_serial() && m > MC;
    let c = &mut c[..m * n];
    // Taken out of the thread-local for the call: while this thread waits in the
    // parallel loop, rayon may run another product on it.
    let mut pack = PACK_B.with(|p| std::mem::take(&mut *p.borrow_mut()));
    for (block, (k0, kc)) in k_blocks(k).enumerate() {
        let load_c = accumulate || block > 0;
        pack_panels(b_op, 0, n, k0, kc, NR, &mut pack);
        let b_words = &pack.words[..];
        let task = |(t, c_rows): (usize, &mut [f32])| {
            let rows = c_rows.len() / n;
            row_block(a_op, t * MC, rows, k0, kc, b_words, n, c_rows, load_c);
        };
        if parallel {
            c.par_chunks_mut(MC * n).enumerate().for_each(task);
        } else {
            c.chunks_mut(MC * n).enumerate().for_each(task);
        }
    }
    PACK_B.with(|p| *p.borrow_mut() = pack);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::learn::amx::{from_bf16, to_bf16};
    use rand::{Rng, SeedableRng};

    fn random(len: usize, seed: u64) -> Vec<f32> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..len).map(|_| rng.gen_range(-1.0f32..1.0)).collect()
    }

    /// `op(x)` value (i, kk) or (kk, j) of a stored operand.
    fn at(x: &[f32], t: bool, rows: usize, cols: usize, r: usize, c: usize) -> f32 {
        if t {
            x[c * rows + r]
        } else {
            x[r * cols + c]
        }
    }

    /// f64 sums of `op(a) op(b)` and of `|op(a)| |op(b)|`, each input passed
    /// through `round` first.
    fn reference(
        s: &GemmShape,
        a: &[f32],
        b: &[f32],
        round: impl Fn(f32) -> f32,
    ) -> (Vec<f64>, Vec<f64>) {
        // op(a) as rows and op(b) as columns, K contiguous in both
        let rows: Vec<f64> = (0..s.m * s.k)
            .map(|e| round(at(a, s.a_t, s.m, s.k, e / s.k, e % s.k)) as f64)
            .collect();
        let cols: Vec<f64> = (0..s.n * s.k)
            .map(|e| round(at(b, s.b_t, s.k, s.n, e % s.k, e / s.k)) as f64)
            .collect();
        let (mut c, mut abs) = (vec![0f64; s.m * s.n], vec![0f64; s.m * s.n]);
        for i in 0..s.m {
            let x = &rows[i * s.k..i * s.k + s.k];
            for j in 0..s.n {
                let y = &cols[j * s.k..j * s.k + s.k];
                let (mut sum, mut sum_abs) = (0.0, 0.0);
                for (p, q) in x.iter().zip(y) {
                    sum += p * q;
                    sum_abs += (p * q).abs();
                }
                c[i * s.n + j] = sum;
                abs[i * s.n + j] = sum_abs;
            }
        }
        (c, abs)
    }

    #[test]
    fn narrow_products_run_in_f32_at_bf16_precision() {
        if !available() {
            eprintln!("no AVX512-BF16 on this CPU: skipped");
            return;
        }
        use crate::learn::mat::{gemm, serial, with_precision, Precision};
        // the action layer forward (n = 12), its dX (k = 12), and a wide product
        for (m, n, k) in [(768, 12, 128), (768, 128, 12), (96, 64, 64)] {
            let (a, b) = (random(m * k, 1), random(k * n, 2));
            let run = |p: Precision| {
                let mut c = vec![0.0f32; m * n];
                with_precision(p, || {
                    serial(|| gemm(m, n, k, &a, false, &b, false, &mut c, false))
                });
                c
            };
            let (f32_c, bf16_c) = (run(Precision::F32), run(Precision::Bf16Avx512));
            if pays_off(n, k) {
                assert_ne!(
                    f32_c, bf16_c,
                    "{m} x {n} x {k}: operands not rounded to bf16"
                );
            } else {
                assert_eq!(f32_c, bf16_c, "{m} x {n} x {k}: not the f32 product");
            }
        }
    }

    #[test]
    fn pairs_are_rounded_to_nearest_even_in_order() {
        if !available() {
            eprintln!("no AVX512-BF16 on this CPU: skipped");
            return;
        }
        let src: Vec<f32> = (0..37).map(|i| 1.0 + i as f32 / 256.0).collect();
        let mut dst = vec![u32::MAX; 19];
        bf16_pairs(&src, &mut dst);
        for (p, &w) in dst.iter().enumerate() {
            assert_eq!(w as u16, to_bf16(src[2 * p]), "pair {p} low");
            let hi = src.get(2 * p + 1).map_or(0, |&x| to_bf16(x));
            assert_eq!((w >> 16) as u16, hi, "pair {p} high");
        }
        let hi: Vec<f32> = src.iter().map(|x| -x).collect();
        let mut dst = vec![u32::MAX; 37];
        interleave_pairs(&src, Some(&hi), &mut dst);
        for (j, &w) in dst.iter().enumerate() {
            assert_eq!(
                (w as u16, (w >> 16) as u16),
                (to_bf16(src[j]), to_bf16(hi[j]))
            );
        }
        interleave_pairs(&src, None, &mut dst);
        assert!(dst.iter().all(|w| w >> 16 == 0));
    }

    /// Every edge (rows, columns, odd K, several K blocks), every transposition,
    /// overwrite and accumulate, serial and on rayon's pool: the f32 sums of the
    /// bf16-rounded inputs, to f32 summation error.
    #[test]
    fn products_match_f64_sums_of_the_rounded_inputs() {
        if !available() {
            eprintln!("no AVX512-BF16 on this CPU: skipped");
            return;
        }
        let round = |x: f32| from_bf16(to_bf16(x));
        for &(m, n, k) in &[
            (1, 1, 1),
            (7, 65, 3),
            (13, 130, 193),
            (97, 64, 64),
            (200, 12, 401),
            (6, 1, 2),
        ] {
            for (a_t, b_t) in [(false, false), (true, false), (false, true), (true, true)] {
                let s = GemmShape {
                    m,
                    n,
                    k,
                    a_t,
                    b_t,
                    what: "",
                };
                let (a, b) = (random(m * k, 1), random(k * n, 2));
                let (want, abs) = reference(&s, &a, &b, round);
                for serial in [true, false] {
                    let mut c = vec![0.5f32; m * n];
                    let run = |c: &mut [f32], acc| gemm_bf16(m, n, k, &a, a_t, &b, b_t, c, acc);
                    if serial {
                        crate::learn::mat::serial(|| run(&mut c, false));
                    } else {
                        run(&mut c, false);
                    }
                    for e in 0..m * n {
                        let tol = (k as f64 + 2.0) * 2f64.powi(-24) * abs[e] + 1e-30;
                        assert!(
                            (c[e] as f64 - want[e]).abs() <= tol,
                            "{m}x{n}x{k} {a_t} {b_t}: {} vs {}",
                            c[e],
                            want[e]
                        );
                    }
                    run(&mut c, true);
                    for e in 0..m * n {
                        let tol = 2.0 * (k as f64 + 3.0) * 2f64.powi(-24) * abs[e] + 1e-30;
                        assert!((c[e] as f64 - 2.0 * want[e]).abs() <= tol, "accumulate");
                    }
                }
            }
        }
    }

    /// The error against the exact product of the f32 inputs, on the learner's
    /// shapes (shards of 768 rows).
    ///
    /// Rounding to bf16 (8 significant bits, nearest even) gives `x (1 + d)` with
    /// `|d| <= u = 2^-8`. A product of two rounded inputs is exact in f32 (16
    /// significant bits), so `a~ b~ = a b (1 + e)`, `|e| <= 2u + u^2`, and summing K
    /// of them in f32 adds at most `gamma_K = K 2^-24 / (1 - K 2^-24)` relative to
    /// `sum |a b|`. Hence, for every element (the deterministic bound, checked):
    ///
    /// `|C_bf16 - C| <= (2u + u^2 + gamma_K) (|A| |B|)_ij`.
    ///
    /// The rounding errors of different inputs are independent with mean zero and
    /// `E d^2 <= u^2 / 3` (uniform over half an ulp, which is at most `u |x|`), so
    /// the typical error is a random walk: `E (C_bf16 - C)_ij^2 <= (2/3) u^2
    /// sum_k (a_ik b_kj)^2 <= (2/3) u^2 K max|a|^2 max|b|^2`, i.e. `sqrt(K) 2^-8`
    /// relative, not `K 2^-8`. Summed over all elements, with `S = sum_k |A_:k|^2
    /// |B_k:|^2`, `E |C_bf16 - C|_F^2 <= (2/3) u^2 S` (checked with factor 1;
    /// nearest-even rounding lands near 0.7 of it, truncation would near 1.4).
    #[test]
    fn error_against_f32_is_within_the_bf16_bound_on_the_learner_shapes() {
        if !available() {
            eprintln!("no AVX512-BF16 on this CPU: skipped");
            return;
        }
        let u = 2f64.powi(-8);
        for (idx, s) in learner_shapes(768, 48, 12).iter().enumerate() {
            let (a, b) = (
                random(s.m * s.k, 10 + idx as u64),
                random(s.k * s.n, 50 + idx as u64),
            );
            let (exact, abs) = reference(s, &a, &b, |x| x);
            let mut c = vec![0f32; s.m * s.n];
            crate::learn::mat::serial(|| {
                gemm_bf16(s.m, s.n, s.k, &a, s.a_t, &b, s.b_t, &mut c, false)
            });
            let kf = s.k as f64 * 2f64.powi(-24);
            let bound = 2.0 * u + u * u + kf / (1.0 - kf);
            let mut err_sq = 0.0;
            for e in 0..s.m * s.n {
                let err = c[e] as f64 - exact[e];
                assert!(
                    err.abs() <= bound * abs[e] + 1e-30,
                    "{}: element {e}",
                    s.what
                );
                err_sq += err * err;
            }
            // S = sum_k |column k of op(a)|^2 |row k of op(b)|^2
            let s_sum: f64 = (0..s.k)
                .map(|kk| {
                    let col: f64 = (0..s.m)
                        .map(|i| (at(&a, s.a_t, s.m, s.k, i, kk) as f64).powi(2))
                        .sum();
                    let row: f64 = (0..s.n)
                        .map(|j| (at(&b, s.b_t, s.k, s.n, kk, j) as f64).powi(2))
                        .sum();
                    col * row
                })
                .sum();
            let typical = (2.0 / 3.0 * u * u * s_sum).sqrt();
            eprintln!(
                "{}: Frobenius error / sqrt(2/3) u sqrt(S) = {:.3}",
                s.what,
                err_sq.sqrt() / typical
            );
            assert!(
                err_sq.sqrt() <= typical,
                "{}: Frobenius error {:.3e} above sqrt(2/3) u sqrt(S) = {typical:.3e}",
                s.what,
                err_sq.sqrt()
            );
        }
    }

    #[test]
    fn k_blocks_cover_k_in_whole_pairs() {
        for k in [1, 2, 3, 191, 192, 193, 256, 512, 768, 1536] {
            let blocks: Vec<_> = k_blocks(k).collect();
            assert_eq!(blocks[0].0, 0);
            assert_eq!(blocks.iter().map(|b| b.1).sum::<usize>(), k, "k {k}");
            for w in blocks.windows(2) {
                assert_eq!(w[0].0 + w[0].1, w[1].0);
                assert_eq!(w[0].1 % 2, 0, "k {k}: a block ends inside a pair");
            }
            assert!(blocks.iter().all(|b| b.1 <= KC_MAX && b.1 > 0));
        }
    }
}
