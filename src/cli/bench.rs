//! `rall bench env`: size runs on your own workstation.

use anyhow::Result;
use clap::{Args, Subcommand, ValueEnum};

use crate::env::bench::bench_env;
use crate::env::terrain::TerrainKind;
use crate::env::EnvConfig;

#[derive(Debug, Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: BenchCommand,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Env steps/s versus the raw physics limit (mj_step x decimation with the same PD).
    Env(EnvBenchArgs),
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
    }
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
