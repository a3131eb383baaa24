//! One PPO update at the default shapes (obs 48, act 12, 256 envs x 24 steps,
//! 5 epochs x 4 mini-batches of 1536) for both critics, next to the plain GEMMs
//! of one mini-batch forward + backward through the same layer shapes.
//! Throughput is reported in matmul FLOP/s (criterion's "elem/s" = FLOP/s).
//!
//! `cargo bench --no-default-features --bench ppo`

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use rall::learn::mat::gemm;
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
        CriticKind::Iqn => {
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

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("ppo");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(12))
        .warm_up_time(Duration::from_secs(2));

    let mut gemm_only = GemmOnly::new(ENVS * STEPS / 4);
    let flops = gemm_only.flops();
    let t = Instant::now();
    for _ in 0..20 {
        gemm_only.run();
    }
    let dt = t.elapsed().as_secs_f64() / 20.0;
    println!(
        "gemm-only mini-batch fwd+bwd (actor + critic shapes, batch 1536): {:.1} ms, {:.1} GFLOP/s",
        dt * 1e3,
        flops / dt / 1e9
    );
    g.throughput(Throughput::Elements(flops as u64));
    g.bench_function("gemm_only_minibatch", |b| b.iter(|| gemm_only.run()));

    for critic in [CriticKind::Iqn, CriticKind::Scalar] {
        let cfg = LearnerConfig {
            critic,
            ..LearnerConfig::default()
        };
        let mut learner = Learner::new(OBS, ACT, &cfg, 0).unwrap();
        let r = rollout(&learner);
        let flops = update_flops(&cfg);
        learner.update(&r).unwrap();
        let t = Instant::now();
        for _ in 0..3 {
            black_box(learner.update(&r).unwrap());
        }
        let dt = t.elapsed().as_secs_f64() / 3.0;
        println!(
            "update {critic:?}: {:.0} ms per update, {:.1} GFLOP/s ({:.1} GFLOP)",
            dt * 1e3,
            flops / dt / 1e9,
            flops / 1e9
        );
        g.throughput(Throughput::Elements(flops as u64));
        g.bench_function(format!("update_{critic:?}").to_lowercase(), |b| {
            b.iter(|| black_box(learner.update(&r).unwrap()))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
