//! Stepping a VecEnv does not grow memory (10k steps with resets).

use std::alloc::{GlobalAlloc, Layout};

use rall::memory::HugePageAlloc;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::sync::Arc;

use rall::env::{build_scene, EnvConfig, VecEnv, ACT_DIM};
use rand::{Rng, SeedableRng};

/// The binary's allocator, counting.
struct Counting;
static LIVE_BYTES: AtomicI64 = AtomicI64::new(0);
static ALLOCS: AtomicU64 = AtomicU64::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        LIVE_BYTES.fetch_add(l.size() as i64, Ordering::Relaxed);
        ALLOCS.fetch_add(1, Ordering::Relaxed);
        unsafe { HugePageAlloc.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        LIVE_BYTES.fetch_sub(l.size() as i64, Ordering::Relaxed);
        unsafe { HugePageAlloc.dealloc(p, l) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn ten_thousand_steps_with_resets_do_not_grow_memory() {
    let mut cfg = EnvConfig {
        robot_mjcf: concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml").into(),
        ..Default::default()
    };
    cfg.episode.length_s = 2.0; // many resets inside the 10k steps
    let cfg = Arc::new(cfg);
    let scene = build_scene(&cfg, 0).unwrap();
    let n = 4;
    let mut v = VecEnv::new(cfg, &scene.model, None, n, 2, 0).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let actions: Vec<f32> = (0..n * ACT_DIM).map(|_| rng.gen_range(-0.5..0.5)).collect();
    let mut episodes = 0;
    // warm-up: thread pool, episode buffer
    for _ in 0..500 {
        v.step(&actions);
        episodes += v.drain_episodes().count();
    }
    let live_before = LIVE_BYTES.load(Ordering::Relaxed);
    let allocs_before = ALLOCS.load(Ordering::Relaxed);
    for _ in 0..10_000 {
        v.step(&actions);
        episodes += v.drain_episodes().count();
    }
    let grown = LIVE_BYTES.load(Ordering::Relaxed) - live_before;
    let allocs = ALLOCS.load(Ordering::Relaxed) - allocs_before;
    assert!(episodes >= 4 * 90, "resets happened: {episodes} episodes");
    assert!(grown <= 0, "live heap grew by {grown} bytes over 10k steps");
    // rayon may allocate a little per parallel call; the env itself does not
    assert!(allocs < 10_000 * 2, "{allocs} allocations in 10k steps");
    println!("10k steps: {allocs} allocations, live heap change {grown} bytes");
}
