//! `rall train`: start or resume a training run.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;

use crate::config::TrainConfig;
use crate::learn::CriticKind;
use crate::runner::{train, LATEST};

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Run configuration (TOML with [env], [learner], [runner]); see configs/.
    #[arg(long, default_value = "configs/flat.toml")]
    pub config: PathBuf,
    /// CVaR level eta of the actor's objective (0.5 = RALL, 1 = risk neutral).
    #[arg(long)]
    pub cvar_eta: Option<f32>,
    /// Critic: iqn (value distribution) or scalar (risk-neutral baseline).
    #[arg(long, value_parser = parse_critic)]
    pub critic: Option<CriticKind>,
    #[arg(long)]
    pub seed: Option<u64>,
    /// Parallel environments.
    #[arg(long)]
    pub envs: Option<usize>,
    /// Env worker threads (0 = all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Iterations to reach (a resumed run continues up to this number).
    #[arg(long)]
    pub iterations: Option<usize>,
    /// Checkpoint every K iterations.
    #[arg(long)]
    pub save_interval: Option<usize>,
    /// Run directory (default: <runs_dir>/<config name>-<critic>-eta<eta>-s<seed>).
    #[arg(long)]
    pub run_dir: Option<PathBuf>,
    /// Resume the run in this directory from its latest checkpoint.
    #[arg(long, conflicts_with = "run_dir")]
    pub resume: Option<PathBuf>,
}

fn parse_critic(s: &str) -> Result<CriticKind, String> {
    match s {
        "iqn" => Ok(CriticKind::Iqn),
        "scalar" => Ok(CriticKind::Scalar),
        other => Err(format!("unknown critic {other:?}: use iqn or scalar")),
    }
}

pub fn run(args: &TrainArgs) -> Result<()> {
    let mut cfg = TrainConfig::from_toml_file(&args.config)?;
    if let Some(eta) = args.cvar_eta {
        cfg.learner.cvar_eta = eta;
    }
    if let Some(c) = args.critic {
        cfg.learner.critic = c;
    }
    if let Some(s) = args.seed {
        cfg.runner.seed = s;
    }
    if let Some(n) = args.envs {
        cfg.runner.num_envs = n;
    }
    if let Some(t) = args.threads {
        cfg.runner.threads = t;
    }
    if let Some(k) = args.iterations {
        cfg.runner.iterations = k;
    }
    if let Some(k) = args.save_interval {
        cfg.runner.save_interval = k;
    }
    cfg.validate().context("after command-line overrides")?;
    let (run_dir, resume) = match (&args.resume, &args.run_dir) {
        (Some(dir), _) => {
            if !dir.join(LATEST).exists() {
                bail!("cannot resume: {} has no {LATEST}", dir.display());
            }
            (dir.clone(), true)
        }
        (None, Some(dir)) => (dir.clone(), false),
        (None, None) => (default_run_dir(&args.config, &cfg), false),
    };
    if !resume && run_dir.join(LATEST).exists() {
        bail!(
            "{} already holds a run; pass --resume {} to continue it or choose another --run-dir",
            run_dir.display(),
            run_dir.display()
        );
    }
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        ctrlc::set_handler(move || {
            if stop.swap(true, Ordering::SeqCst) {
                eprintln!("second Ctrl-C: exiting without a checkpoint");
                std::process::exit(130);
            }
            eprintln!("Ctrl-C: finishing this iteration and writing a checkpoint (Ctrl-C again to abort)");
        })
        .context("installing the Ctrl-C handler")?;
    }
    println!(
        "training {} envs x {} steps, critic {:?}, eta {}, seed {} -> {}",
        cfg.runner.num_envs,
        cfg.runner.steps_per_env,
        cfg.learner.critic,
        cfg.learner.cvar_eta,
        cfg.runner.seed,
        run_dir.display()
    );
    let summary = train(cfg, &run_dir, resume, stop, &mut ())?;
    println!(
        "{} at iteration {}; checkpoint {}",
        if summary.interrupted { "stopped" } else { "finished" },
        summary.iterations_done,
        summary.last_checkpoint.display()
    );
    Ok(())
}

fn default_run_dir(config: &std::path::Path, cfg: &TrainConfig) -> PathBuf {
    let name = config.file_stem().and_then(|s| s.to_str()).unwrap_or("run");
    let critic = match cfg.learner.critic {
        CriticKind::Iqn => "iqn",
        CriticKind::Scalar => "scalar",
    };
    PathBuf::from(&cfg.runner.runs_dir).join(format!("{name}-{critic}-eta{}-s{}", cfg.learner.cvar_eta, cfg.runner.seed))
}
