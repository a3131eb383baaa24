//! `rall bench env`: size runs on your own workstation. `rall bench comm`
//! (under mpirun): what the data-parallel update's sums cost on your network.
//! `rall bench scaling`: where an iteration's time goes on 1 and 2 threads, and
//! its projection to more cores (`runner::scaling`).

use anyhow::Result;
use clap::{Args, Subcommand, ValueEnum};

use crate::config::TrainConfig;
use crate::env::bench::bench_env;
use crate::env::terrain::TerrainKind;
use crate::env::{EnvConfig, ACT_DIM};
use crate::learn::{Collective, Learner};
use crate::runner::World;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: BenchCommand,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Env steps/s versus the raw physics limit (mj_step x decimation with the same PD).
    Env(EnvBenchArgs),
    /// Under `mpirun -np N`: time of the update's all-reduces (the learner's
    /// gradient size from a config) and their projected cost at 16 and 64 ranks.
    Comm(CommBenchArgs),
    /// Training iterations of a config on 1 and 2 threads, phase by phase, and a
    /// projection to more cores (Amdahl per phase; the assumptions are printed).
    Scaling(ScalingBenchArgs),
}

#[derive(Debug, Args)]
pub struct ScalingBenchArgs {
    /// Run configuration (envs, steps per env, networks, PPO settings).
    #[arg(long, default_value = "configs/flat.toml")]
    pub config: std::path::PathBuf,
    /// Timed iterations per thread count (after the warm-up ones).
    #[arg(long, default_value_t = 5)]
    pub iterations: usize,
    /// Untimed iterations first.
    #[arg(long, default_value_t = 2)]
    pub warmup: usize,
    /// Core counts to project to.
    #[arg(long, default_values_t = [16, 64])]
    pub cores: Vec<usize>,
    /// Envs per core of the projected machine [default: the config's envs / 2].
    #[arg(long)]
    pub envs_per_core: Option<f64>,
    /// Parallel efficiency per core of the update's GEMMs [default: measured from 1 to 2 threads].
    #[arg(long)]
    pub gemm_efficiency: Option<f64>,
}

#[derive(Debug, Args)]
pub struct CommBenchArgs {
    /// Run configuration whose networks set the gradient size.
    #[arg(long, default_value = "configs/rall.toml")]
    pub config: std::path::PathBuf,
    /// Timed all-reduces per message size.
    #[arg(long, default_value_t = 100)]
    pub repeats: usize,
    /// Network bandwidth (Gbit/s) of the projection's cluster.
    #[arg(long, default_value_t = 25.0)]
    pub net_gbps: f64,
    /// Network latency (microseconds per message) of the projection's cluster.
    #[arg(long, default_value_t = 20.0)]
    pub net_latency_us: f64,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum TerrainArg {
    Flat,
    Rough,
}

#[derive(Debug, Args)]
pub struct EnvBenchArgs {
    #[arg(long, default_value_t = 256)]
    pub envs: usize,
    /// Worker threads; several values compare scaling (e.g. --threads 1 --threads 2).
    #[arg(long, default_value = "1")]
    pub threads: Vec<usize>,
    #[arg(long, value_enum, default_value_t = TerrainArg::Flat)]
    pub terrain: TerrainArg,
    /// Seconds per measurement (split between the env and the raw loop).
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Robot MJCF.
    #[arg(long, default_value = "mjcf/aliengo.xml")]
    pub robot: String,
}

pub fn run(args: &BenchArgs) -> Result<()> {
    match &args.what {
        BenchCommand::Env(a) => env(a),
        BenchCommand::Comm(a) => comm(a),
        BenchCommand::Scaling(a) => scaling(a),
    }
}

fn scaling(a: &ScalingBenchArgs) -> Result<()> {
    use crate::runner::scaling::{measure, phases, report, Target};
    anyhow::ensure!(a.iterations > 0, "--iterations must be at least 1");
    anyhow::ensure!(a.cores.iter().all(|&c| c > 0), "--cores must be positive");
    if let Some(e) = a.envs_per_core {
        anyhow::ensure!(
            e.is_finite() && e > 0.0,
            "--envs-per-core must be positive, got {e}"
        );
    }
    if let Some(e) = a.gemm_efficiency {
        anyhow::ensure!(
            e.is_finite() && e > 0.0 && e <= 1.0,
            "--gemm-efficiency must be in (0, 1], got {e}"
        );
    }
    let cfg = TrainConfig::from_toml_file(&a.config)?;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if cores < 2 {
        eprintln!("warning: {cores} core here: the 2-thread measurement shares it, so the serial fractions read high");
    }
    let r = &cfg.runner;
    println!(
        "{}: {} envs x {} steps, {} epochs x {} mini-batches, matmul {:?}; {} + {} iterations per thread count",
        a.config.display(),
        r.num_envs,
        r.steps_per_env,
        cfg.learner.ppo.num_learning_epochs,
        cfg.learner.ppo.num_mini_batches,
        cfg.learner.ppo.matmul,
        a.warmup,
        a.iterations
    );
    let one = measure(&cfg, 1, a.warmup, a.iterations)?;
    let two = measure(&cfg, 2, a.warmup, a.iterations)?;
    let measured = phases(&one, &two);
    let gemm_efficiency = a
        .gemm_efficiency
        .unwrap_or_else(|| (one.gemm_s / (2.0 * two.gemm_s).max(1e-12)).min(1.0));
    let targets: Vec<Target> = [1, 2]
        .iter()
        .chain(&a.cores)
        .map(|&c| Target {
            cores: c,
            envs_measured: r.num_envs,
            envs_per_core: a.envs_per_core.unwrap_or(r.num_envs as f64 / 2.0),
            gemm_efficiency,
        })
        .collect();
    print!("{}", report(&measured, &targets, r.steps_per_env));
    Ok(())
}

fn env(a: &EnvBenchArgs) -> Result<()> {
    anyhow::ensure!(a.envs > 0, "--envs must be at least 1");
    let mut cfg = EnvConfig {
        robot_mjcf: a.robot.clone(),
        ..Default::default()
    };
    cfg.terrain.kind = match a.terrain {
        TerrainArg::Flat => TerrainKind::Flat,
        TerrainArg::Rough => TerrainKind::Rough,
    };
    println!(
        "{} envs, {:?} terrain, random actions U[-0.5, 0.5], {} s per run",
        a.envs, a.terrain, a.seconds
    );
    println!("threads | env steps/s | raw physics (policy steps/s) | env/raw | speed-up vs first");
    let mut first = None;
    for &t in &a.threads {
        let r = bench_env(&cfg, a.envs, t, a.seconds, 1)?;
        let base = *first.get_or_insert(r.env_steps_per_s);
        println!(
            "{:>7} | {:>11.0} | {:>28.0} | {:>7.3} | {:>6.2}x",
            t,
            r.env_steps_per_s,
            r.raw_steps_per_s,
            r.ratio(),
            r.env_steps_per_s / base
        );
    }
    Ok(())
}

/// Median seconds of `repeats` sums of `n` floats across the ranks (each
/// preceded by a one-value sum, so that ranks start together).
fn time_sum(world: &World, n: usize, repeats: usize) -> f64 {
    let mut v = vec![1.0f32; n];
    let mut sync = [0.0f64];
    let mut times = Vec::with_capacity(repeats);
    for k in 0..repeats + 5 {
        world.sum_f64(&mut sync);
        let t = Instant::now();
        world.sum_f32(&mut v);
        if k >= 5 {
            times.push(t.elapsed().as_secs_f64());
        }
    }
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

/// Ring all-reduce model: `T(p) = 2 (p - 1) alpha + 2 (p - 1) / p x bytes x beta`.
fn ring_s(p: usize, bytes: f64, alpha_s: f64, beta_s_per_byte: f64) -> f64 {
    let p = p as f64;
    2.0 * (p - 1.0) * alpha_s + 2.0 * (p - 1.0) / p * bytes * beta_s_per_byte
}

fn comm(a: &CommBenchArgs) -> Result<()> {
    let world = World::from_env()?;
    let p = world.size();
    anyhow::ensure!(
        p >= 2,
        "run this under an MPI launcher with two or more processes, e.g. `mpirun -np 2 rall bench comm`"
    );
    let cfg = TrainConfig::from_toml_file(&a.config)?;
    let learner = Learner::with_layout(&cfg.env.obs_layout(), ACT_DIM, &cfg.learner, 0)?;
    let ac = learner.actor_critic();
    // what `ppo::update` sums per mini-batch: both gradients and 4 statistics
    let floats = ac.actor.params.len() + ac.critic.params().len() + 4;
    let bytes = 4.0 * floats as f64;
    let (epochs, n_mb) = (
        cfg.learner.ppo.num_learning_epochs,
        cfg.learner.ppo.num_mini_batches,
    );
    let per_iter = epochs * n_mb;
    let moments_bytes = 24.0 * n_mb as f64;
    let t_small = time_sum(&world, 1, a.repeats);
    let t_grad = time_sum(&world, floats, a.repeats);
    if !world.is_root() {
        return Ok(());
    }
    let alpha = t_small / (2.0 * (p as f64 - 1.0));
    let beta = ((t_grad - 2.0 * (p as f64 - 1.0) * alpha)
        / (2.0 * (p as f64 - 1.0) / p as f64 * bytes))
        .max(0.0);
    let (net_alpha, net_beta) = (a.net_latency_us * 1e-6, 8.0 / (a.net_gbps * 1e9));
    println!(
        "{} ranks; {}: {floats} floats ({:.2} MB) per gradient all-reduce, {per_iter} per iteration ({} epochs x {} mini-batches), plus one advantage-moment sum per epoch",
        p,
        a.config.display(),
        bytes / 1e6,
        epochs,
        n_mb
    );
    println!(
        "measured (median of {}): 1 float {:.1} us, gradient {:.3} ms ({:.2} GB/s effective); per iteration {:.1} ms",
        a.repeats,
        t_small * 1e6,
        t_grad * 1e3,
        bytes / t_grad / 1e9,
        (per_iter as f64 * t_grad + epochs as f64 * t_small) * 1e3
    );
    println!(
        "ring model fitted here: latency {:.1} us, {:.2} GB/s per link; a cluster: {} us, {} Gbit/s",
        alpha * 1e6,
        1.0 / beta.max(1e-15) / 1e9,
        a.net_latency_us,
        a.net_gbps
    );
    println!("ranks | this machine's links: ms per iteration | the cluster's: ms per iteration");
    for ranks in [2, 16, 64] {
        let iter = |al: f64, be: f64| {
            (per_iter as f64 * ring_s(ranks, bytes, al, be)
                + epochs as f64 * ring_s(ranks, moments_bytes, al, be))
                * 1e3
        };
        println!(
            "{ranks:>5} | {:>38.1} | {:>30.1}",
            iter(alpha, beta),
            iter(net_alpha, net_beta)
        );
    }
    Ok(())
}
