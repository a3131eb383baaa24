//! The learner's matrix products on AMX tiles in bf16 (`learn::amx`) against the
//! f32 kernels it uses today (`learn::mat::gemm`, AVX-512), side by side on one
//! thread, on the shapes of one PPO shard (768 rows: a 1,536-sample mini-batch
//! split over two threads) of the [512, 256, 128] networks. The learner uses
//! these kernels with `[learner.ppo] matmul = "bf16"` (opt-in: see the learning
//! curves in docs/research-log.md).
//!
//! `cargo bench --bench amx` (prints "no AMX" and exits on CPUs without it).

/// The allocator the `rall` binary runs with (large buffers on huge pages).
#[global_allocator]
static ALLOCATOR: rall::memory::HugePageAlloc = rall::memory::HugePageAlloc;

use std::time::Instant;

use rall::learn::{amx, mat};

/// (m, n, k, a transposed, b transposed, what).
const SHAPES: [(usize, usize, usize, bool, bool, &str); 6] = [
    (768, 512, 48, false, false, "forward 48 -> 512"),
    (768, 256, 512, false, false, "forward 512 -> 256"),
    (768, 128, 256, false, false, "forward 256 -> 128"),
    (768, 512, 256, false, true, "backward dX 256 -> 512"),
    (512, 256, 768, true, false, "backward dW 512 x 256"),
    (256, 128, 768, true, false, "backward dW 256 x 128"),
];

fn median_s(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    let mut t: Vec<f64> = (0..reps)
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(|a, b| a.total_cmp(b));
    t[reps / 2]
}

fn main() {
    if !amx::available() {
        println!("no AMX-BF16 on this CPU (or the OS does not grant it): nothing to compare");
        return;
    }
    println!("one thread, medians of 101 calls, interleaved per shape:");
    let (mut f32_total, mut amx_total) = (0.0, 0.0);
    for (m, n, k, a_t, b_t, what) in SHAPES {
        let a: Vec<f32> = (0..m * k)
            .map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5)
            .collect();
        let b: Vec<f32> = (0..k * n)
            .map(|i| ((i * 104729) % 1000) as f32 / 1000.0 - 0.5)
            .collect();
        let mut c = vec![0f32; m * n];
        let flop = 2.0 * (m * n * k) as f64;
        let tf =
            mat::serial(|| median_s(101, || mat::gemm(m, n, k, &a, a_t, &b, b_t, &mut c, false)));
        let ta = median_s(101, || {
            amx::gemm_bf16(m, n, k, &a, a_t, &b, b_t, &mut c, false)
        });
        f32_total += tf;
        amx_total += ta;
        println!(
            "  {what:24} {m:4} x {n:3} x {k:3}: f32 {:7.1} us ({:4.0} GFLOP/s), amx bf16 {:7.1} us ({:4.0} GFLOP/s), ratio {:.2}",
            tf * 1e6,
            flop / tf / 1e9,
            ta * 1e6,
            flop / ta / 1e9,
            tf / ta
        );
    }
    println!(
        "  all six: f32 {:.2} ms, amx bf16 {:.2} ms, ratio {:.2}",
        f32_total * 1e3,
        amx_total * 1e3,
        f32_total / amx_total
    );
}
