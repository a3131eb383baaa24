//! The `rall` command line (clap). Each subcommand lives in its own file.

pub mod bench;
pub mod calibrate;
pub mod checkpoint;
pub mod eval;
pub mod experiment;
pub mod export;
pub mod inspect;
pub mod play;
pub mod train;

use clap::{Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(
    name = "rall",
    version,
    about = "Risk-averse legged locomotion (RALL): train, evaluate and inspect quadruped policies on CPU"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Print a model's bodies, joints, actuators and mass, and check that the robot stands under PD.
    Inspect(inspect::InspectArgs),
    /// Train a policy (CVaR-PPO with an IQN critic, or the scalar baseline).
    Train(train::TrainArgs),
    /// Watch a policy in the rerun viewer: robot, terrain, commands, value distribution, IQR.
    Play(play::PlayArgs),
    /// Evaluate checkpoints (tracking; robustness benchmarks).
    Eval(eval::EvalArgs),
    /// Run an experiment file: train what is missing, resume what is unfinished, skip what is done, evaluate with the paper's protocol, write tables and figures.
    Experiment(experiment::ExperimentArgs),
    /// Export a checkpoint's policy to ONNX with a JSON sidecar for a robot controller (`--help`: the 50 Hz robot loop).
    Export(export::ExportArgs),
    /// Measure throughput (env steps/s versus the raw physics limit).
    Bench(bench::BenchArgs),
    /// Set per-joint risk thresholds from a walking policy's gait (a quantile of |joint
    /// velocity|, |acceleration|, |torque| per joint) and write them into a config.
    CalibrateRisk(calibrate::CalibrateRiskArgs),
    /// What a checkpoint file holds (iteration, method, checksums, whether it resumes
    /// exactly), and its actor-only copy for evaluation.
    Checkpoint(checkpoint::CheckpointArgs),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Inspect(args) => inspect::run(&args),
        Command::Train(args) => train::run(&args),
        Command::Play(args) => play::run(&args),
        Command::Eval(args) => eval::run(&args),
        Command::Experiment(args) => experiment::run(&args),
        Command::Export(args) => export::run(&args),
        Command::Bench(args) => bench::run(&args),
        Command::CalibrateRisk(args) => calibrate::run(&args),
        Command::Checkpoint(args) => checkpoint::run(&args),
    }
}
