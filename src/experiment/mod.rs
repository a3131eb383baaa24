//! `rall experiment FILE`: the paper's campaign from one file. Trains what is
//! missing, resumes what is unfinished, skips what is done; then evaluates every
//! policy with the paper's protocol (tracking, table I TTF, table II platform
//! drops, race track with the IQR meta controller; with `[commands]`, each run's
//! command-space safety map; each registered benchmark with its section, see
//! [`benchmark`]) and writes tables beside the paper's numbers, CSV/JSON with
//! every cell, bootstrap intervals and figures.

pub mod benchmark;
mod clock;
pub mod command_plots;
pub mod commands;
mod commands_report;
pub mod contrasts;
pub mod critic_tail;
pub mod curve_plots;
pub mod curves;
mod evaluate;
mod final_policy;
mod ladder;
pub mod last_checkpoints;
pub mod plots;
pub mod pooled;
pub mod results;
pub mod risk_signal;
pub mod selection;
mod ship;
pub mod spec;
pub mod stats;
mod status;
mod training;
pub mod verdicts;

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use anyhow::{bail, Context, Result};

use crate::config::TrainConfig;
use crate::runner::Progress;
pub use benchmark::{register_benchmark, Benchmark, BenchmarkContext, BenchmarkOutput};
pub use clock::PhaseTime;
pub use evaluate::{calibrate_threshold, evaluate_all};
pub use final_policy::{choose_final_policies, newest_checkpoint, selected_checkpoint};
pub use results::{ExperimentResults, RunTracking, TrackingEstimates};
pub use ship::{restore_shipped, ship_all};
pub use spec::ExperimentSpec;
pub use status::status_lines;
pub use training::train_all;

/// What to do.
#[derive(Debug, Clone)]
pub struct ExperimentOptions {
    pub train: bool,
    pub evaluate: bool,
    /// Evaluate unfinished runs at their latest checkpoint instead of refusing.
    pub allow_unfinished: bool,
    /// Run every rollout, neither reading nor storing the rollout cache.
    pub fresh_rollouts: bool,
}

/// A run's state on disk.
#[derive(Debug, Clone)]
pub struct RunState {
    pub dir: PathBuf,
    /// Iterations to reach (PPO + RMA's phase 2).
    pub target: usize,
    pub progress: Option<Progress>,
}

impl RunState {
    pub fn done(&self) -> bool {
        self.progress
            .as_ref()
            .is_some_and(|p| p.iteration >= self.target)
    }
}

/// The config of run `r` as the experiment trains it.
pub fn run_config(spec: &ExperimentSpec, r: &spec::RunSpec) -> Result<TrainConfig> {
    let mut cfg =
        TrainConfig::from_toml_file(&r.config).with_context(|| format!("run {:?}", r.label))?;
    cfg.runner.seed = r.seed;
    cfg.runner.iterations = r.iterations;
    cfg.runner.threads = spec.threads;
    Ok(cfg)
}

/// The iterations run `r` with config `cfg` trains to: PPO's, then RMA's phase 2.
fn target_iterations(r: &spec::RunSpec, cfg: &TrainConfig) -> usize {
    r.iterations + cfg.learner.adaptation.as_ref().map_or(0, |a| a.iterations)
}

/// The iterations run `r` trains to, from its config alone (no checkpoint read).
pub fn run_target(spec: &ExperimentSpec, r: &spec::RunSpec) -> Result<usize> {
    Ok(target_iterations(r, &run_config(spec, r)?))
}

/// Where run `r` stands (reads its newest readable checkpoint).
pub fn run_state(spec: &ExperimentSpec, r: &spec::RunSpec) -> Result<RunState> {
    let cfg = run_config(spec, r)?;
    let target = target_iterations(r, &cfg);
    let dir = spec.run_dir(r);
    let progress = match newest_checkpoint(spec, r)? {
        Some(path) => {
            let loaded = crate::runner::load_policy(&path)?;
            // what a resume would train: the stored config with this budget and last stage
            let stored = crate::runner::train::keep_runner_settings(
                loaded.config.clone(),
                &cfg,
                loaded.progress.iteration,
            )
            .with_context(|| format!("run {:?} ({})", r.label, path.display()))?;
            let changed = learning_differences(&stored, &cfg);
            if !changed.is_empty() {
                bail!(
                    "run {:?}: its checkpoint {} was trained with another config than {} now gives \
                     (differs in {}); move the run's directory away (and its shipped copy) to \
                     retrain it, or give the run a new name",
                    r.label,
                    path.display(),
                    r.config.display(),
                    changed.join(", ")
                );
            }
            Some(loaded.progress)
        }
        None => None,
    };
    Ok(RunState {
        dir,
        target,
        progress,
    })
}

/// Dotted keys in which two run configs differ, leaving out the runner keys that
/// do not change what is learned (budget, threads, logging and checkpoint cadence)
/// and the history group RMA's phase 2 adds.
pub fn learning_differences(a: &TrainConfig, b: &TrainConfig) -> Vec<String> {
    let comparable = |c: &TrainConfig| {
        let mut c = c.clone();
        c.runner.iterations = 0;
        c.runner.threads = 0;
        c.runner.save_interval = 1;
        c.runner.log_interval = 1;
        c.runner.runs_dir.clear();
        // RMA's phase 2 adds the history group itself (runner::adapt)
        if c.learner.adaptation.is_some() {
            let history = crate::env::observation::ObsGroup::History;
            c.env.observation.groups.retain(|g| *g != history);
        }
        toml::Value::try_from(c).ok()
    };
    let mut out = Vec::new();
    match (comparable(a), comparable(b)) {
        (Some(x), Some(y)) => value_differences("", &x, &y, &mut out),
        _ => out.push("(a config that cannot be written as TOML)".into()),
    }
    out
}

fn value_differences(at: &str, a: &toml::Value, b: &toml::Value, out: &mut Vec<String>) {
    match (a, b) {
        (toml::Value::Table(x), toml::Value::Table(y)) => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            for k in keys {
                let key = if at.is_empty() {
                    k.clone()
                } else {
                    format!("{at}.{k}")
                };
                match (x.get(k), y.get(k)) {
                    (Some(u), Some(v)) => value_differences(&key, u, v, out),
                    _ => out.push(key),
                }
            }
        }
        _ if a != b => out.push(at.to_string()),
        _ => {}
    }
}

/// Trains (if asked), evaluates (if asked) and writes the results.
pub fn run_experiment(
    spec: &ExperimentSpec,
    opts: &ExperimentOptions,
    stop: Arc<AtomicBool>,
) -> Result<()> {
    if opts.train {
        train_all(spec, stop)?;
    }
    if opts.evaluate {
        let results = evaluate_all(spec, opts)?;
        results.write(&spec.results_dir)?;
        eprintln!("results in {}", spec.results_dir.display());
    }
    Ok(())
}
