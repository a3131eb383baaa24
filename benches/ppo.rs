//! One PPO update at the default shapes (obs 48, act 12, 256 envs x 24 steps,
//! 5 epochs x 4 mini-batches of 1536) for both critics, next to the plain GEMMs
//! of one mini-batch forward + backward through the same layer shapes.
//! Throughput is reported in matmul FLOP/s (criterion's "elem/s" = FLOP/s).
//!
//! `cargo bench --no-default-features --bench ppo`: first a table of old (gemm 0.15,
//! AVX2) against new (gemm 0.19, AVX-512 at run time) kernels on 1 and 2 threads,
//! then every matmul precision this CPU runs (`f32`; `bf16` on AMX tiles;
//! `bf16-avx512` on AVX512-BF16) side by side, per GEMM shape of a mini-batch shard
//! and for a whole update, then criterion's own measurement of each.

/// The allocator the `rall` binary runs with (large buffers on huge pages).
#[global_allocator]
static ALLOCATOR: rall::memory::HugePageAlloc = rall::memory::HugePageAlloc;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use rall::learn::bf16_avx512::{learner_shapes, GemmShape};
use rall::learn::mat::{self, gemm, precision_available, precision_backend, Kernels, Precision};
use rall::learn::{CriticKind, Learner, LearnerConfig, Rollout};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hint::black_box;
use std::time::{Duration, Instant};

const OBS: usize = 48;
const ACT: usize = 12;
const ENVS: usize = 256;
const STEPS: usize = 24;

fn rollout(learner: &Learner) -> Rollout {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut r = Rollout::new(STEPS, ENVS, OBS, ACT);
    for t in 0..STEPS {
        let obs: Vec<f32> = (0..ENVS * OBS).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let out = learner.act(&obs, &mut rng);
        let rew: Vec<f32> = (0..ENVS).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let done: Vec<bool> = (0..ENVS).map(|e| (e + t) % 50 == 0).collect();
        let tout: Vec<bool> = (0..ENVS).map(|e| (e + t) % 100 == 0).collect();
        r.push(&obs, &out, &rew, &done, &tout, &obs).unwrap();
    }
    r.set_last_obs(&vec![0.1; ENVS * OBS]).unwrap();
    r
}

/// Matmul FLOPs of forward + backward (dW always, dX except for the first layer).
fn mlp_flops(dims: &[usize], batch: usize) -> f64 {
    dims.windows(2)
        .enumerate()
        .map(|(l, d)| {
            let f = 2.0 * (batch * d[0] * d[1]) as f64;
            if l == 0 {
                2.0 * f
            } else {
                3.0 * f
            }
        })
        .sum()
}

/// Matmul FLOPs of one update.
fn update_flops(cfg: &LearnerConfig) -> f64 {
    let total = ENVS * STEPS;
    let b = total / cfg.ppo.num_mini_batches;
    let n_mb = (cfg.ppo.num_learning_epochs * cfg.ppo.num_mini_batches) as f64;
    let actor: Vec<usize> = [&[OBS][..], &cfg.actor_hidden, &[ACT]].concat();
    let f = *cfg.critic_hidden.last().unwrap();
    let per_mb_actor = mlp_flops(&actor, b);
    let (per_mb_critic, prepass) = match cfg.critic {
        CriticKind::Scalar => {
            let dims: Vec<usize> = [&[OBS][..], &cfg.critic_hidden, &[1]].concat();
            let fwd = mlp_flops(&dims, total + ENVS) / 3.0 * 1.5; // forward only
            (mlp_flops(&dims, b), fwd)
        }
        _ => {
            // IQN
            let dims: Vec<usize> = [&[OBS][..], &cfg.critic_hidden].concat();
            let (n, c) = (cfg.num_taus, cfg.num_cos);
            let embed = 2.0 * 2.0 * (n * c * f) as f64;
            let head = 3.0 * 2.0 * (b * n * f) as f64;
            let taus = cfg.num_value_taus + cfg.num_target_taus;
            let trunk_fwd: f64 = dims
                .windows(2)
                .map(|d| 2.0 * ((total + ENVS) * d[0] * d[1]) as f64)
                .sum();
            let pre =
                trunk_fwd + 2.0 * ((total + ENVS) * taus * f) as f64 + 2.0 * (taus * c * f) as f64;
            (mlp_flops(&dims, b) + embed + head, pre)
        }
    };
    n_mb * (per_mb_actor + per_mb_critic) + prepass
}

/// The GEMMs alone of one mini-batch forward + backward through the actor and
/// the scalar critic shapes (what a perfect implementation would still pay).
struct GemmOnly {
    layers: Vec<(usize, usize, Vec<f32>)>,
    bufs: Vec<Vec<f32>>,
    batch: usize,
}

impl GemmOnly {
    fn new(batch: usize) -> Self {
        let mut layers = Vec::new();
        for dims in [[OBS, 512, 256, 128, ACT], [OBS, 512, 256, 128, 1]] {
            for d in dims.windows(2) {
                layers.push((d[0], d[1], vec![0.01; d[0] * d[1]]));
            }
        }
        GemmOnly {
            bufs: vec![vec![0.5; batch * 512]; 4],
            layers,
            batch,
        }
    }
    fn flops(&self) -> f64 {
        let b = self.batch;
        mlp_flops(&[OBS, 512, 256, 128, ACT], b) + mlp_flops(&[OBS, 512, 256, 128, 1], b)
    }
    fn run(&mut self) {
        let b = self.batch;
        let [x, y, dy, dx] = &mut self.bufs[..] else {
            unreachable!()
        };
        let mut dw = vec![0.0; 512 * 256];
        for (l, (i, o, w)) in self.layers.iter().enumerate() {
            gemm(b, *o, *i, x, false, w, false, y, false);
            gemm(*i, *o, b, x, true, dy, false, &mut dw, true);
            if l % 4 != 0 {
                gemm(b, *i, *o, dy, false, w, true, dx, false);
            }
        }
        black_box(&dw);
    }
}

/// Mean seconds of `f` over `reps` runs after one warm-up.
fn time_it(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    let t = Instant::now();
    for _ in 0..reps {
        f();
    }
    t.elapsed().as_secs_f64() / reps as f64
}

fn learner(critic: CriticKind) -> (Learner, Rollout, f64) {
    learner_at(critic, Precision::F32)
}

/// A default learner whose update runs its matrix products at `matmul`.
fn learner_at(critic: CriticKind, matmul: Precision) -> (Learner, Rollout, f64) {
    let mut cfg = LearnerConfig {
        critic,
        ..LearnerConfig::default()
    };
    cfg.ppo.matmul = matmul;
    let learner = Learner::new(OBS, ACT, &cfg, 0).unwrap();
    let r = rollout(&learner);
    let flops = update_flops(&cfg);
    (learner, r, flops)
}

/// Old (gemm 0.15, AVX2 on stable) and new (gemm 0.19, run-time AVX-512) kernels,
/// on 1 and 2 threads, interleaved in one run so the ratios share the machine's state.
fn summary() {
    println!("CPU SIMD level for Kernels::Auto: {}", mat::simd_level());
    if let Ok(critic) = std::env::var("PPO_BENCH_PROFILE") {
        // only updates with the new kernels, for `perf record`
        let critic = if critic == "scalar" {
            CriticKind::Scalar
        } else {
            CriticKind::Iqn
        };
        let (mut l, r, _) = learner(critic);
        for _ in 0..10 {
            black_box(l.update(&r).unwrap());
        }
        std::process::exit(0);
    }
    let mut gemm_only = GemmOnly::new(ENVS * STEPS / 4);
    let gflops = gemm_only.flops();
    let mut rows = Vec::new();
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let (mut l, r, flops) = learner(critic);
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut t = [0.0; 2];
            let mut g = [0.0; 2];
            // two rounds, alternating kernels, keep each one's best
            for _round in 0..2 {
                for (i, k) in [Kernels::Legacy, Kernels::Auto].into_iter().enumerate() {
                    mat::set_kernels(k);
                    let dt = pool.install(|| {
                        time_it(2, || {
                            black_box(l.update(&r).unwrap());
                        })
                    });
                    let dg = pool.install(|| time_it(10, || gemm_only.run()));
                    t[i] = if t[i] == 0.0 { dt } else { f64::min(t[i], dt) };
                    g[i] = if g[i] == 0.0 { dg } else { f64::min(g[i], dg) };
                }
            }
            mat::set_kernels(Kernels::Auto);
            rows.push((critic, threads, t, g, flops));
        }
    }
    println!("| critic | threads | update old (ms) | update new (ms) | new/old speed-up | update GFLOP/s old / new | plain GEMM GFLOP/s old / new |");
    println!("|---|---|---|---|---|---|---|");
    for (critic, threads, t, g, flops) in &rows {
        println!(
            "| {critic:?} | {threads} | {:.0} | {:.0} | {:.2}x | {:.0} / {:.0} | {:.0} / {:.0} |",
            t[0] * 1e3,
            t[1] * 1e3,
            t[0] / t[1],
            flops / t[0] / 1e9,
            flops / t[1] / 1e9,
            gflops / g[0] / 1e9,
            gflops / g[1] / 1e9
        );
    }
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let (mut l, r, _) = learner(critic);
        l.update(&r).unwrap();
        let t = l.update(&r).unwrap().time;
        println!(
            "update phases ({critic:?}, new kernels, all threads): targets {:.0} ms, gather {:.0}, forward {:.0}, loss {:.0}, backward {:.0}, clip {:.0}, adam {:.0} (total {:.0} ms)",
            t.targets_s * 1e3,
            t.gather_s * 1e3,
            t.forward_s * 1e3,
            t.loss_s * 1e3,
            t.backward_s * 1e3,
            t.clip_s * 1e3,
            t.adam_s * 1e3,
            t.total_s() * 1e3
        );
    }
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let one = rows.iter().find(|r| r.0 == critic && r.1 == 1).unwrap();
        let two = rows.iter().find(|r| r.0 == critic && r.1 == 2).unwrap();
        println!(
            "2-thread speed-up of the update ({critic:?}): old kernels {:.2}x, new kernels {:.2}x",
            one.2[0] / two.2[0],
            one.2[1] / two.2[1]
        );
    }
}

/// The matmul precisions this CPU runs natively (named as in the config), and a
/// line for each one it does not.
fn precisions() -> Vec<(&'static str, Precision)> {
    let all = [
        ("f32", Precision::F32),
        ("bf16-amx", Precision::Bf16),
        ("bf16-avx512", Precision::Bf16Avx512),
    ];
    all.into_iter()
        .filter(|&(name, p)| {
            let ok = precision_available(p);
            if !ok {
                println!("{name}: not measured ({})", precision_backend(p));
            }
            ok
        })
        .collect()
}

/// Operands and output of one GEMM shape.
struct ShapeData {
    s: GemmShape,
    a: Vec<f32>,
    b: Vec<f32>,
    c: Vec<f32>,
}

fn shape_data(rows: usize) -> Vec<ShapeData> {
    let value = |i: usize, p: usize| ((i * p) % 1000) as f32 / 1000.0 - 0.5;
    learner_shapes(rows, OBS, ACT)
        .into_iter()
        .map(|s| ShapeData {
            a: (0..s.m * s.k).map(|i| value(i, 7919)).collect(),
            b: (0..s.k * s.n).map(|i| value(i, 104_729)).collect(),
            c: vec![0.0; s.m * s.n],
            s,
        })
        .collect()
}

/// One GEMM on the calling thread at `p` (as a PPO shard runs it).
fn run_shape(d: &mut ShapeData, p: Precision) {
    let s = d.s;
    mat::with_precision(p, || {
        mat::serial(|| gemm(s.m, s.n, s.k, &d.a, s.a_t, &d.b, s.b_t, &mut d.c, false))
    });
}

/// Median seconds of `reps` runs of `f` after one warm-up.
fn median_s(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    let mut t: Vec<f64> = (0..reps)
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[reps / 2]
}

/// Every precision side by side: each GEMM shape of one 768-row shard (one thread,
/// interleaved per shape), then one whole update per critic on 1 and 2 threads.
fn precision_summary(paths: &[(&'static str, Precision)]) {
    println!("GEMM shapes of one 768-row shard, one thread, medians of 51 calls (us, GFLOP/s):");
    let mut total = vec![0.0; paths.len()];
    for d in &mut shape_data(768) {
        let flop = 2.0 * (d.s.m * d.s.n * d.s.k) as f64;
        let mut line = format!("  {:26} {:4} x {:3} x {:4}:", d.s.what, d.s.m, d.s.n, d.s.k);
        for (i, &(name, p)) in paths.iter().enumerate() {
            let t = median_s(51, || run_shape(d, p));
            total[i] += t;
            line += &format!(" {name} {:7.1} ({:4.0})", t * 1e6, flop / t / 1e9);
        }
        println!("{line}");
    }
    for (i, &(name, _)) in paths.iter().enumerate() {
        println!(
            "  all shapes, {name}: {:.2} ms, {:.2}x f32",
            total[i] * 1e3,
            total[0] / total[i]
        );
    }
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut line = format!("update ({critic:?}, {threads} threads):");
            let mut first = 0.0;
            for &(name, p) in paths {
                let (mut l, r, flops) = learner_at(critic, p);
                let t = pool.install(|| {
                    time_it(2, || {
                        black_box(l.update(&r).unwrap());
                    })
                });
                if first == 0.0 {
                    first = t;
                }
                line += &format!(
                    " {name} {:.0} ms ({:.0} GFLOP/s, {:.2}x f32)",
                    t * 1e3,
                    flops / t / 1e9,
                    first / t
                );
            }
            println!("{line}");
        }
    }
}

fn bench(c: &mut Criterion) {
    summary();
    let paths = precisions();
    precision_summary(&paths);
    let mut g = c.benchmark_group("gemm_shard");
    g.sample_size(20)
        .measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_secs(1));
    let mut shapes = shape_data(768);
    let flops: f64 = shapes
        .iter()
        .map(|d| 2.0 * (d.s.m * d.s.n * d.s.k) as f64)
        .sum();
    g.throughput(Throughput::Elements(flops as u64));
    for &(name, p) in &paths {
        g.bench_function(format!("all_shapes_768_rows_{name}"), |b| {
            b.iter(|| shapes.iter_mut().for_each(|d| run_shape(d, p)))
        });
    }
    g.finish();
    let mut g = c.benchmark_group("ppo");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(8))
        .warm_up_time(Duration::from_secs(2));
    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let (mut learner, r, flops) = learner(critic);
        g.throughput(Throughput::Elements(flops as u64));
        for k in [Kernels::Legacy, Kernels::Auto] {
            mat::set_kernels(k);
            g.bench_function(format!("update_{critic:?}_{k:?}").to_lowercase(), |b| {
                b.iter(|| black_box(learner.update(&r).unwrap()))
            });
        }
        mat::set_kernels(Kernels::Auto);
        for &(name, p) in paths.iter().filter(|(_, p)| *p != Precision::F32) {
            let (mut learner, r, _) = learner_at(critic, p);
            g.bench_function(format!("update_{critic:?}_{name}").to_lowercase(), |b| {
                b.iter(|| black_box(learner.update(&r).unwrap()))
            });
        }
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
