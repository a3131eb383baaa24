//! VecEnv policy steps/s versus the raw physics limit (mj_step x 4 with the
//! same PD law, same robots), flat then rough, 1 and 2 threads, in one run.
//! Targets: env/raw >= 0.90; 2 threads >= 1.8x one. Prints a summary table.

/// The allocator the `rall` binary runs with (large buffers on huge pages).
#[global_allocator]
static ALLOCATOR: rall::memory::HugePageAlloc = rall::memory::HugePageAlloc;

use criterion::{criterion_group, criterion_main, Criterion};
use rall::env::bench::bench_env;
use rall::env::terrain::TerrainKind;
use rall::env::EnvConfig;

fn bench(_c: &mut Criterion) {
    let envs = 64;
    println!("env summary: {envs} envs, random actions; env and raw loops interleaved");
    for terrain in [TerrainKind::Flat, TerrainKind::Rough] {
        let mut cfg = EnvConfig {
            robot_mjcf: concat!(env!("CARGO_MANIFEST_DIR"), "/mjcf/aliengo.xml").into(),
            ..Default::default()
        };
        cfg.terrain.kind = terrain;
        let one = bench_env(&cfg, envs, 1, 8.0, 1).expect("bench");
        let two = bench_env(&cfg, envs, 2, 8.0, 1).expect("bench");
        for r in [one, two] {
            println!(
                "env summary: {terrain:?} threads {} | env {:.0} steps/s | raw {:.0} steps/s | env/raw {:.3}",
                r.threads,
                r.env_steps_per_s,
                r.raw_steps_per_s,
                r.ratio()
            );
        }
        println!(
            "env summary: {terrain:?} 2-thread speed-up: env {:.2}x, raw {:.2}x",
            two.env_steps_per_s / one.env_steps_per_s,
            two.raw_steps_per_s / one.raw_steps_per_s
        );
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
