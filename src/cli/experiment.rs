//! `rall experiment FILE`: train, resume or skip every run of an experiment
//! file, then evaluate them with the paper's protocol and write the results.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::Args;

use crate::experiment::results::ExperimentResults;
use crate::experiment::{
    run_experiment, ship_all, status_lines, ExperimentOptions, ExperimentSpec,
};

#[derive(Debug, Args)]
pub struct ExperimentArgs {
    /// Experiment file (e.g. experiments/paper.toml): runs, evaluations, the paper's numbers.
    pub file: PathBuf,
    /// Only train (resume, skip) the runs.
    #[arg(long, conflicts_with_all = ["eval_only", "status"])]
    pub train_only: bool,
    /// Only evaluate the trained runs and write the results.
    #[arg(long, conflicts_with = "status")]
    pub eval_only: bool,
    /// Evaluate runs that have not reached their budget at their latest checkpoint
    /// (the tables mark them unfinished).
    #[arg(long)]
    pub allow_unfinished: bool,
    /// Run every evaluation rollout again, neither reading nor storing the
    /// rollout cache (`<runs_dir>/rollout-cache`, which lets a stopped
    /// evaluation resume and a repeated one run only what changed).
    #[arg(long, conflicts_with = "train_only")]
    pub fresh_rollouts: bool,
    /// Print where every run stands and exit.
    #[arg(long)]
    pub status: bool,
    /// Copy every run's latest checkpoint, config and metrics to the file's
    /// `shipped_dir` (to commit them) and exit.
    #[arg(long, conflicts_with_all = ["status", "train_only", "eval_only"])]
    pub ship: bool,
    /// Write the README (with the file's current `preface`), the CSV tables and the
    /// figures of the file's results_dir again from its results.json with the
    /// current code (nothing is evaluated) and exit.
    #[arg(long, conflicts_with_all = ["status", "train_only", "eval_only", "ship"])]
    pub redraw: bool,
    /// Print, from the between-seed spread in the file's results_dir, the seeds per
    /// method Welch's test needs for 80% power on the `[verdicts]` contrasts, and exit.
    #[arg(long, conflicts_with_all = ["status", "train_only", "eval_only", "ship", "redraw"])]
    pub power: bool,
    /// With --power: also the seeds needed to detect this difference (the metric's units).
    #[arg(long, value_name = "DIFFERENCE", requires = "power")]
    pub effect: Option<f64>,
    /// With --train-only: train only the run with this label (repeat it), so that
    /// several runs of one experiment train side by side, one process each.
    #[arg(long = "run", value_name = "LABEL", requires = "train_only")]
    pub runs: Vec<String>,
    /// With --train-only: worker threads for this process (default: the file's `threads`).
    #[arg(long, value_name = "N", requires = "train_only")]
    pub threads: Option<usize>,
}

/// `spec` narrowed to the runs labelled in `labels` (all when empty); an unknown
/// label is refused, naming the labels the file has.
fn only_runs(mut spec: ExperimentSpec, labels: &[String]) -> Result<ExperimentSpec> {
    if labels.is_empty() {
        return Ok(spec);
    }
    for l in labels {
        if spec.run(l).is_none() {
            let known: Vec<&str> = spec.runs.iter().map(|r| r.label.as_str()).collect();
            bail!(
                "--run {l:?}: the experiment file has no run with that label (it has: {})",
                known.join(", ")
            );
        }
    }
    spec.runs.retain(|r| labels.contains(&r.label));
    Ok(spec)
}

pub fn run(args: &ExperimentArgs) -> Result<()> {
    let mut spec = only_runs(ExperimentSpec::from_file(&args.file)?, &args.runs)?;
    if let Some(n) = args.threads {
        crate::learn::ppo::check_count("--threads", n, 0, crate::config::MAX_THREADS)?;
        spec.threads = n;
    }
    if args.ship {
        return ship_all(&spec, &args.file);
    }
    if args.redraw {
        for f in ExperimentResults::redraw(&spec.results_dir, spec.preface_text()?, Some(&spec))? {
            println!("{}", f.display());
        }
        return Ok(());
    }
    if args.power {
        let results = ExperimentResults::read(&spec.results_dir)?;
        for line in
            crate::experiment::verdicts::power_lines(&spec, &results.contrasts, args.effect)?
        {
            println!("{line}");
        }
        return Ok(());
    }
    if args.status {
        for line in status_lines(&spec)? {
            println!("{line}");
        }
        return Ok(());
    }
    let opts = ExperimentOptions {
        train: !args.eval_only,
        evaluate: !args.train_only,
        allow_unfinished: args.allow_unfinished,
        fresh_rollouts: args.fresh_rollouts,
    };
    let stop = super::train::install_stop_handler()?;
    run_experiment(&spec, &opts, stop)
}
