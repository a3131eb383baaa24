//! Matrix products on Intel AMX tiles: inputs rounded to bf16, products summed in
//! f32 (`TDPBF16PS`), for CPUs that have AMX-BF16 (Sapphire Rapids and later).
//! One tile instruction does 16 x 16 x 32 multiply-adds; measured on one core of
//! this machine's CPU, 3.7 TFLOP/s against ~0.15 for f32 AVX-512 FMA.
//!
//! [`gemm_bf16`] has [`super::mat::gemm`]'s contract. It packs `op(a)` into bf16
//! rows and `op(b)` into the pair-interleaved ("VNNI") layout the tiles read, both
//! zero-padded to whole tiles, then computes 32 x 32 blocks of `c` with four
//! accumulator tiles. Single-threaded: the PPO update already runs one shard of
//! each mini-batch per thread (inside [`super::mat::serial`]).
//!
//! The tile instructions are written with `asm!` (the AMX intrinsics are not
//! stable Rust); Linux grants AMX state to a process on request
//! (`arch_prctl(ARCH_REQ_XCOMP_PERM)`), which [`available`] makes once.

use std::sync::OnceLock;

/// Rows of a tile.
const TILE_ROWS: usize = 16;
/// bf16 values in a tile row (64 bytes).
const TILE_K: usize = 32;
/// Rows and columns of `c` computed per block (2 x 2 tiles).
const BLOCK: usize = 32;

/// Whether this process can run AMX-BF16 tiles: the CPU has them, the OS saves
/// their state, and Linux granted this process the tile data. Asked once.
pub fn available() -> bool {
    static AVAILABLE: OnceLock<bool> = OnceLock::new();
    *AVAILABLE.get_or_init(detect)
}

#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
fn detect() -> bool {
    use std::arch::x86_64::{__cpuid, __cpuid_count};
    // cpuid is available on every x86_64 CPU (a safe intrinsic since Rust 1.87).
    let (leaf1, leaf7) = (__cpuid(1), __cpuid_count(7, 0));
    let amx_bf16 = leaf7.edx & (1 << 22) != 0;
    let amx_tile = leaf7.edx & (1 << 24) != 0;
    let osxsave = leaf1.ecx & (1 << 27) != 0;
    if !(amx_bf16 && amx_tile && osxsave) {
        return false;
    }
    // XCR0 bits 17 (XTILECFG) and 18 (XTILEDATA): the OS saves tile state.
    let xcr0: u64 = {
        let (lo, hi): (u32, u32);
        // SAFETY: xgetbv(0) is valid when OSXSAVE is set (checked above).
        unsafe {
            std::arch::asm!("xgetbv", in("ecx") 0u32, out("eax") lo, out("edx") hi,
                options(nomem, nostack, preserves_flags));
        }
        (hi as u64) << 32 | lo as u64
    };
    if xcr0 & (0b11 << 17) != 0b11 << 17 {
        return false;
    }
    request_tile_data()
}

#[cfg(not(target_arch = "x86_64"))]
fn detect() -> bool {
    false
}

/// Linux: `arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`, without which
/// the first tile instruction kills the process.
#[cfg(all(target_arch = "x86_64", target_os = "linux"))]
#[allow(unsafe_code)]
fn request_tile_data() -> bool {
    const ARCH_REQ_XCOMP_PERM: libc::c_long = 0x1023;
    const XFEATURE_XTILEDATA: libc::c_long = 18;
    // SAFETY: a plain syscall with two integer arguments.
    unsafe {
        libc::syscall(
            libc::SYS_arch_prctl,
            ARCH_REQ_XCOMP_PERM,
            XFEATURE_XTILEDATA,
        ) == 0
    }
}

#[cfg(all(target_arch = "x86_64", not(target_os = "linux")))]
fn request_tile_data() -> bool {
    false
}

/// `x` rounded to the nearest bf16 (ties to even), as its bits; NaN stays NaN.
/// Branch-free, so the packing loops vectorise.
#[inline(always)]
pub fn to_bf16(x: f32) -> u16 {
    let b = x.to_bits();
    let rounded = b.wrapping_add(0x7fff + ((b >> 16) & 1)) >> 16;
    let quiet_nan = (b >> 16) | 0x40;
    let is_nan = (b & 0x7fff_ffff) > 0x7f80_0000;
    (if is_nan { quiet_nan } else { rounded }) as u16
}

/// The f32 value of bf16 bits.
#[inline(always)]
pub fn from_bf16(h: u16) -> f32 {
    f32::from_bits((h as u32) << 16)
}

fn round_up(x: usize, to: usize) -> usize {
    x.div_ceil(to) * to
}

/// Scratch buffers reused between calls on a thread.
#[derive(Default)]
struct Packs {
    a: Vec<u16>,
    b: Vec<u16>,
    /// An operand converted as it lies, before its transpose or interleave.
    tmp: Vec<u16>,
}

thread_local! {
    static PACKS: std::cell::RefCell<Packs> = std::cell::RefCell::new(Packs::default());
}

/// Side of the blocks transposes are done in (cache-friendly reads and writes).
const T_BLOCK: usize = 64;

/// `dst[i] = bf16(src[i])`: 16 at a time with AVX512-BF16's `VCVTNEPS2BF16`
/// (round to nearest even, as [`to_bf16`]; it also reads subnormals as zero).
fn convert(src: &[f32], dst: &mut [u16]) {
    debug_assert_eq!(src.len(), dst.len());
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512bf16") {
        // SAFETY: the CPU has the features the function is compiled for.
        #[allow(unsafe_code)]
        unsafe {
            convert_avx512bf16(src, dst)
        };
        return;
    }
    for (d, &s) in dst.iter_mut().zip(src) {
        *d = to_bf16(s);
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
#[allow(unsafe_code)]
fn convert_avx512bf16(src: &[f32], dst: &mut [u16]) {
    use std::arch::x86_64::{__m256i, _mm256_storeu_si256, _mm512_cvtneps_pbh, _mm512_loadu_ps};
    let n = src.len().min(dst.len());
    let whole = n / 16 * 16;
    for i in (0..whole).step_by(16) {
        // SAFETY: i + 16 <= n bounds both the 16-float read and the 16-u16 write.
        unsafe {
            let v = _mm512_loadu_ps(src.as_ptr().add(i));
            let h: __m256i = std::mem::transmute(_mm512_cvtneps_pbh(v));
            _mm256_storeu_si256(dst.as_mut_ptr().add(i) as *mut __m256i, h);
        }
    }
    for i in whole..n {
        dst[i] = to_bf16(src[i]);
    }
}

/// `src` (rows x cols, row-major) converted to bf16 into `out`.
fn convert_rows(src: &[f32], rows: usize, cols: usize, out: &mut Vec<u16>) {
    out.clear();
    out.resize(rows * cols, 0);
    convert(&src[..rows * cols], out);
}

/// `t[c][r] = s[r][c]` for `s` rows x cols (u16), block by block.
fn transpose_into(s: &[u16], rows: usize, cols: usize, t: &mut [u16], t_stride: usize) {
    for r0 in (0..rows).step_by(T_BLOCK) {
        for c0 in (0..cols).step_by(T_BLOCK) {
            for r in r0..(r0 + T_BLOCK).min(rows) {
                let row = &s[r * cols..r * cols + cols];
                for c in c0..(c0 + T_BLOCK).min(cols) {
                    t[c * t_stride + r] = row[c];
                }
            }
        }
    }
}

/// `op(a)` (m x k) as bf16 rows of `kp` values, `mp` rows, zero-padded.
fn pack_a(a: &[f32], a_t: bool, m: usize, k: usize, mp: usize, kp: usize, p: &mut Packs) {
    p.a.clear();
    p.a.resize(mp * kp, 0);
    if a_t {
        // a is k x m: converted as it lies, then transposed as 16-bit values.
        convert_rows(a, k, m, &mut p.tmp);
        transpose_into(&p.tmp, k, m, &mut p.a, kp);
    } else {
        for i in 0..m {
            convert(&a[i * k..i * k + k], &mut p.a[i * kp..i * kp + k]);
        }
    }
}

/// `op(b)` (k x n) in the tiles' pair-interleaved layout: row `kk / 2` holds, for
/// every column `j`, `b[kk][j]` then `b[kk + 1][j]`; `kp / 2` rows of `2 np`.
fn pack_b(b: &[f32], b_t: bool, k: usize, n: usize, kp: usize, np: usize, p: &mut Packs) {
    p.b.clear();
    p.b.resize(kp * np, 0);
    let width = 2 * np;
    if b_t {
        // b is n x k: each row j holds column j of op(b) with its pairs (kk, kk + 1)
        // side by side, so pairs move as u32 in a transpose of n x (k / 2) pairs.
        convert_rows(b, n, k, &mut p.tmp);
        let pairs = k.div_ceil(2);
        super::mat::with_simd(|| {
            for p0 in (0..pairs).step_by(T_BLOCK) {
                for j in 0..n {
                    let row = &p.tmp[j * k..j * k + k];
                    for pair in p0..(p0 + T_BLOCK).min(pairs) {
                        let kk = 2 * pair;
                        let o = pair * width + 2 * j;
                        p.b[o] = row[kk];
                        if kk + 1 < k {
                            p.b[o + 1] = row[kk + 1];
                        }
                    }
                }
            }
        });
    } else {
        // Rows kk and kk + 1 zipped into one pair-row.
        convert_rows(b, k, n, &mut p.tmp);
        super::mat::with_simd(|| {
            for pair in 0..k.div_ceil(2) {
                let r0 = &p.tmp[2 * pair * n..2 * pair * n + n];
                let dst = &mut p.b[pair * width..pair * width + 2 * n];
                if 2 * pair + 1 < k {
                    let r1 = &p.tmp[(2 * pair + 1) * n..(2 * pair + 1) * n + n];
                    for ((d, &x), &y) in dst.chunks_exact_mut(2).zip(r0).zip(r1) {
                        d[0] = x;
                        d[1] = y;
                    }
                } else {
                    for (d, &x) in dst.chunks_exact_mut(2).zip(r0) {
                        d[0] = x;
                    }
                }
            }
        });
    }
}

/// The tile configuration (64 bytes, `LDTILECFG`'s operand).
#[repr(C, align(64))]
struct TileConfig {
    palette: u8,
    start_row: u8,
    reserved: [u8; 14],
    colsb: [u16; 16],
    rows: [u8; 16],
}

/// Tiles 0-3: 16 x 16 f32 accumulators; 4-5: 16 rows of 32 bf16 of `a`; 6-7: 16
/// pair-rows of 16 columns of `b`. Every tile is 16 rows of 64 bytes.
fn tile_config() -> TileConfig {
    let mut c = TileConfig {
        palette: 1,
        start_row: 0,
        reserved: [0; 14],
        colsb: [0; 16],
        rows: [0; 16],
    };
    for t in 0..8 {
        c.colsb[t] = 64;
        c.rows[t] = TILE_ROWS as u8;
    }
    c
}

/// `c[m x n] = (accumulate ? c : 0) + op(a) op(b)`, as [`super::mat::gemm`], with
/// `op(a)` and `op(b)` rounded to bf16 and the products summed in f32 on AMX tiles.
/// Call only when [`available`].
#[allow(clippy::too_many_arguments)]
#[allow(unsafe_code)]
#[cfg(target_arch = "x86_64")]
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
    assert!(available(), "AMX tiles are not available to this process");
    super::mat::assert_gemm_dims(m, n, k, a.len(), b.len(), c.len());
    if m == 0 || n == 0 {
        return;
    }
    let (mp, np, kp) = (
        round_up(m, BLOCK),
        round_up(n, BLOCK),
        round_up(k.max(1), TILE_K),
    );
    PACKS.with(|p| {
        let p = &mut *p.borrow_mut();
        pack_a(a, a_t, m, k, mp, kp, p);
        pack_b(b, b_t, k, n, kp, np, p);
        let cfg = tile_config();
        let a_stride = kp * 2; // bytes per row of packed a
        let b_stride = np * 4; // bytes per pair-row of packed b (2 np bf16)
        let mut block = [0f32; BLOCK * BLOCK];
        // SAFETY: AMX is available (asserted); the configuration gives every tile
        // 16 rows of 64 bytes. Loads read 16 rows of 64 bytes at `ptr + r * stride`:
        // a-tiles start at row i0 (+16) < mp and column kb * 32, and mp x kp bf16
        // are allocated; b-tiles start at pair-row kb * 16 (< kp / 2) and byte
        // column 4 * j0 (+64) < 4 np, and kp / 2 pair-rows of 4 np bytes are
        // allocated. Accumulators are loaded from and stored to `c` itself only for a
        // whole block (i0 + 32 <= m, j0 + 32 <= n: 32 rows of 32 f32 at row stride n,
        // inside the m x n floats asserted above); otherwise stored into `block`
        // (32 x 32 f32, rows of 128 bytes) at offsets within it.
        unsafe {
            std::arch::asm!("ldtilecfg [{}]", in(reg) &cfg as *const TileConfig);
            for i0 in (0..mp).step_by(BLOCK) {
                for j0 in (0..np).step_by(BLOCK) {
                    // A whole block of c is read and written by the tiles themselves.
                    let whole = i0 + BLOCK <= m && j0 + BLOCK <= n;
                    let c_block = c.as_mut_ptr().add(i0 * n + j0);
                    let c_stride = n * 4;
                    if whole && accumulate {
                        std::arch::asm!(
                            "tileloadd tmm0, [{c0} + {s} * 1]",
                            "tileloadd tmm1, [{c1} + {s} * 1]",
                            "tileloadd tmm2, [{c2} + {s} * 1]",
                            "tileloadd tmm3, [{c3} + {s} * 1]",
                            c0 = in(reg) c_block,
                            c1 = in(reg) c_block.add(TILE_ROWS),
                            c2 = in(reg) c_block.add(TILE_ROWS * n),
                            c3 = in(reg) c_block.add(TILE_ROWS * n + TILE_ROWS),
                            s = in(reg) c_stride,
                            options(nostack),
                        );
                    } else {
                        std::arch::asm!(
                            "tilezero tmm0",
                            "tilezero tmm1",
                            "tilezero tmm2",
                            "tilezero tmm3"
                        );
                    }
                    for kb in 0..kp / TILE_K {
                        let a0 = p.a.as_ptr().add(i0 * kp + kb * TILE_K);
                        let a1 = a0.add(TILE_ROWS * kp);
                        let b0 = p.b.as_ptr().add(kb * TILE_ROWS * 2 * np + 2 * j0);
                        let b1 = b0.add(2 * TILE_ROWS);
                        std::arch::asm!(
                            "tileloadd tmm4, [{a0} + {sa} * 1]",
                            "tileloadd tmm5, [{a1} + {sa} * 1]",
                            "tileloadd tmm6, [{b0} + {sb} * 1]",
                            "tileloadd tmm7, [{b1} + {sb} * 1]",
                            "tdpbf16ps tmm0, tmm4, tmm6",
                            "tdpbf16ps tmm1, tmm4, tmm7",
                            "tdpbf16ps tmm2, tmm5, tmm6",
                            "tdpbf16ps tmm3, tmm5, tmm7",
                            a0 = in(reg) a0,
                            a1 = in(reg) a1,
                            b0 = in(reg) b0,
                            b1 = in(reg) b1,
                            sa = in(reg) a_stride,
                            sb = in(reg) b_stride,
                            options(nostack),
                        );
                    }
                    let (out, stride) = if whole {
                        (c_block, c_stride)
                    } else {
                        (block.as_mut_ptr(), BLOCK * 4)
                    };
                    std::arch::asm!(
                        "tilestored [{c0} + {s} * 1], tmm0",
                        "tilestored [{c1} + {s} * 1], tmm1",
                        "tilestored [{c2} + {s} * 1], tmm2",
                        "tilestored [{c3} + {s} * 1], tmm3",
                        c0 = in(reg) out,
                        c1 = in(reg) out.add(TILE_ROWS),
                        c2 = in(reg) out.add(TILE_ROWS * stride / 4),
                        c3 = in(reg) out.add(TILE_ROWS * stride / 4 + TILE_ROWS),
                        s = in(reg) stride,
                        options(nostack),
                    );
                    if !whole {
                        write_block(&block, c, m, n, i0, j0, accumulate);
                    }
                }
            }
            std::arch::asm!("tilerelease");
        }
    });
}

/// Copies (or adds) the valid part of a 32 x 32 block into `c` at (i0, j0).
fn write_block(
    block: &[f32; BLOCK * BLOCK],
    c: &mut [f32],
    m: usize,
    n: usize,
    i0: usize,
    j0: usize,
    accumulate: bool,
) {
    let cols = BLOCK.min(n - j0);
    for r in 0..BLOCK.min(m - i0) {
        let src = &block[r * BLOCK..r * BLOCK + cols];
        let dst = &mut c[(i0 + r) * n + j0..(i0 + r) * n + j0 + cols];
        if accumulate {
            dst.iter_mut().zip(src).for_each(|(d, s)| *d += s);
        } else {
            dst.copy_from_slice(src);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values(len: usize, seed: u32) -> Vec<f32> {
        (0..len)
            .map(|i| (((i as u32).wrapping_mul(2654435761) ^ seed) % 2001) as f32 / 1000.0 - 1.0)
            .collect()
    }

    /// f32 reference of op(a) op(b) from the bf16-rounded inputs.
    #[allow(clippy::too_many_arguments)]
    fn reference(
        m: usize,
        n: usize,
        k: usize,
        a: &[f32],
        a_t: bool,
        b: &[f32],
        b_t: bool,
    ) -> Vec<f32> {
        let r = |x: f32| from_bf16(to_bf16(x));
        let mut c = vec![0f32; m * n];
        for i in 0..m {
            for j in 0..n {
                let mut s = 0f64;
                for kk in 0..k {
                    let av = if a_t { a[kk * m + i] } else { a[i * k + kk] };
                    let bv = if b_t { b[j * k + kk] } else { b[kk * n + j] };
                    s += r(av) as f64 * r(bv) as f64;
                }
                c[i * n + j] = s as f32;
            }
        }
        c
    }

    #[test]
    fn bf16_rounding_is_to_nearest_even() {
        assert_eq!(to_bf16(1.0), 0x3f80);
        assert_eq!(from_bf16(to_bf16(-2.5)), -2.5);
        // 1 + 2^-8 is halfway between 1 and 1 + 2^-7: ties go to the even (1.0).
        assert_eq!(from_bf16(to_bf16(1.0 + 1.0 / 256.0)), 1.0);
        assert_eq!(from_bf16(to_bf16(1.0 + 3.0 / 256.0)), 1.0 + 4.0 / 256.0);
        assert!(from_bf16(to_bf16(f32::NAN)).is_nan());
        assert_eq!(from_bf16(to_bf16(f32::INFINITY)), f32::INFINITY);
    }

    #[test]
    fn products_match_f32_sums_of_the_rounded_inputs() {
        if !available() {
            eprintln!("no AMX on this machine: skipped");
            return;
        }
        // Odd sizes (edges of every tile), whole blocks (tiles read and write c
        // directly), both transposes, overwrite and accumulate.
        for &(m, n, k) in &[
            (1, 1, 1),
            (17, 33, 45),
            (40, 12, 48),
            (70, 1, 130),
            (33, 64, 31),
            (64, 96, 64),
        ] {
            for (a_t, b_t) in [(false, false), (true, false), (false, true), (true, true)] {
                let a = values(m * k, 1);
                let b = values(k * n, 2);
                let want = reference(m, n, k, &a, a_t, &b, b_t);
                let mut c = vec![0.5f32; m * n];
                gemm_bf16(m, n, k, &a, a_t, &b, b_t, &mut c, false);
                for (x, y) in c.iter().zip(&want) {
                    assert!(
                        (x - y).abs() <= 1e-4 * (1.0 + y.abs()),
                        "{m}x{n}x{k}: {x} vs {y}"
                    );
                }
                gemm_bf16(m, n, k, &a, a_t, &b, b_t, &mut c, true);
                for (x, y) in c.iter().zip(&want) {
                    assert!(
                        (x - 2.0 * y).abs() <= 2e-4 * (1.0 + y.abs()),
                        "accumulate {m}x{n}x{k}"
                    );
                }
            }
        }
    }
}
