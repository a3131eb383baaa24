//! What a page of memory costs to touch again after it sat idle, on 4 KiB pages
//! against 2 MiB transparent huge pages (the reason for `rall::memory`).
//!
//! 8 MiB either as one vector (at least `memory::HUGE_MIN_BYTES`: huge pages
//! through the crate's allocator) or as 32 vectors of 256 KiB (below it: 4 KiB
//! pages); every 4 KiB touched once after sleeping 0-800 ms. Interleaved, medians
//! of 5. `cargo bench --bench memory`.

/// The allocator the `rall` binary runs with (large buffers on huge pages).
#[global_allocator]
static ALLOCATOR: rall::memory::HugePageAlloc = rall::memory::HugePageAlloc;

use std::time::{Duration, Instant};

const BYTES: usize = 8 << 20;

fn touch(bufs: &mut [Vec<f32>]) {
    for b in bufs.iter_mut() {
        for page in b.chunks_mut(1024) {
            page[0] += 1.0;
        }
    }
}

fn median_after_idle(bufs: &mut [Vec<f32>], idle: Duration) -> f64 {
    let mut t: Vec<f64> = (0..5)
        .map(|_| {
            std::thread::sleep(idle);
            let t0 = Instant::now();
            touch(bufs);
            t0.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(|a, b| a.total_cmp(b));
    t[2]
}

fn main() {
    let small = 256 << 10;
    assert!(small < rall::memory::HUGE_MIN_BYTES && BYTES >= rall::memory::HUGE_MIN_BYTES);
    let mut pages_4k: Vec<Vec<f32>> = (0..BYTES / small).map(|_| vec![1.0; small / 4]).collect();
    let mut pages_2m = vec![vec![1.0f32; BYTES / 4]];
    println!("touch every 4 KiB of 8 MiB after it sat idle (medians of 5):");
    for idle_ms in [0u64, 50, 200, 800] {
        let idle = Duration::from_millis(idle_ms);
        let small_s = median_after_idle(&mut pages_4k, idle);
        let huge_s = median_after_idle(&mut pages_2m, idle);
        println!(
            "  idle {idle_ms:4} ms: 4 KiB pages {:8.2} ms, 2 MiB pages {:6.2} ms, ratio {:6.1}",
            small_s * 1e3,
            huge_s * 1e3,
            small_s / huge_s
        );
    }
    let thp = std::fs::read_to_string("/sys/kernel/mm/transparent_hugepage/enabled")
        .unwrap_or_else(|_| "unknown".into());
    println!("transparent huge pages: {}", thp.trim());
}
