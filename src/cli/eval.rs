//! `rall eval ...`: evaluation commands.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, Subcommand};

use crate::eval::{evaluate_tracking, tracking_env, ActionMode};
use crate::runner::load_policy;

#[derive(Debug, Args)]
pub struct EvalArgs {
    #[command(subcommand)]
    pub what: EvalCommand,
}

#[derive(Debug, Subcommand)]
pub enum EvalCommand {
    /// Velocity-command tracking on flat ground (noise and PD as in training).
    Tracking(TrackingArgs),
}

#[derive(Debug, Args)]
pub struct TrackingArgs {
    /// Checkpoint (.safetensors) written by `rall train`.
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// Robots, one full episode each (run in parallel).
    #[arg(long, default_value_t = 64)]
    pub episodes: usize,
    #[arg(long, default_value_t = 12345)]
    pub seed: u64,
    /// Worker threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Sample actions from the policy's Gaussian as in training (default: its mean).
    #[arg(long)]
    pub stochastic: bool,
}

pub fn run(args: &EvalArgs) -> Result<()> {
    match &args.what {
        EvalCommand::Tracking(a) => tracking(a),
    }
}

fn threads(n: usize) -> usize {
    if n == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        n
    }
}

fn tracking(a: &TrackingArgs) -> Result<()> {
    anyhow::ensure!(a.episodes > 0, "--episodes must be at least 1");
    let policy = load_policy(&a.checkpoint)?;
    let env = tracking_env(&policy.config.env);
    let mode = if a.stochastic { ActionMode::Sampled } else { ActionMode::Mean };
    let r = evaluate_tracking(&policy.learner, &env, a.episodes, threads(a.threads), a.seed, mode)?;
    println!(
        "checkpoint {} (iteration {}, {} env steps)",
        a.checkpoint.display(),
        policy.progress.iteration,
        policy.progress.total_env_steps
    );
    println!("episodes             {} ({:?} actions)", r.episodes, mode);
    println!("lin-vel tracking     {:.3}   (mean exp(-|v_cmd - v|^2 / sigma), 1 = perfect)", r.lin_vel_score);
    println!("yaw-rate tracking    {:.3}", r.yaw_rate_score);
    println!(
        "fall rate            {:.1}%   (trunk contact {}, tilt {}, physics failure {})",
        100.0 * r.fall_rate,
        r.trunk_contacts,
        r.tilts,
        r.unstable
    );
    println!("mean episode length  {:.0} / {} steps", r.mean_episode_length_steps, r.max_episode_length_steps);
    Ok(())
}
