//! `rall train`: start or resume a training run.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;

use crate::config::TrainConfig;
use crate::learn::CriticKind;
use crate::runner::{train, LATEST};
use crate::viz::{RerunTarget, TrainRecorder, TrainRecordingOptions};

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
    /// Also record the run for rerun into this .rrd file (metrics per iteration,
    /// evaluation episodes); no viewer needed.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["rerun_spawn", "rerun_connect"])]
    pub rerun_save: Option<PathBuf>,
    /// Also record the run to a rerun viewer started from PATH.
    #[arg(long, conflicts_with = "rerun_connect")]
    pub rerun_spawn: bool,
    /// Also record the run to a running rerun viewer (default 127.0.0.1:9876).
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:9876")]
    pub rerun_connect: Option<String>,
    /// With a rerun recording: one evaluation episode every K iterations (0 = none).
    #[arg(long, value_name = "K", default_value_t = 50)]
    pub rerun_eval_every: usize,
    /// With a rerun recording: policy steps of an evaluation episode.
    #[arg(long, value_name = "N", default_value_t = 500)]
    pub rerun_eval_steps: usize,
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
            eprintln!(
                "Ctrl-C: finishing this iteration and writing a checkpoint (Ctrl-C again to abort)"
            );
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
    let target = RerunTarget::from_flags(
        args.rerun_save.as_deref(),
        args.rerun_spawn,
        args.rerun_connect.as_deref(),
    );
    let summary = match target {
        None => train(cfg, &run_dir, resume, stop, &mut ())?,
        Some(target) => {
            // A resumed run evaluates in its own stored env.
            let stored = run_dir.join("config.toml");
            let run_cfg = if resume && stored.exists() {
                TrainConfig::from_toml_file(&stored)?
            } else {
                cfg.clone()
            };
            let opts = TrainRecordingOptions {
                eval_every: args.rerun_eval_every,
                eval_steps: args.rerun_eval_steps,
            };
            let mut recorder =
                TrainRecorder::open(&target, &run_dir.display().to_string(), &run_cfg, opts)?;
            let summary = train(cfg, &run_dir, resume, stop, &mut recorder)?;
            recorder.finish()?;
            if let RerunTarget::Save(path) = &target {
                println!(
                    "rerun recording: {} (open with `rerun {}`)",
                    path.display(),
                    path.display()
                );
            }
            summary
        }
    };
    println!(
        "{} at iteration {}; checkpoint {}",
        if summary.interrupted {
            "stopped"
        } else {
            "finished"
        },
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
    PathBuf::from(&cfg.runner.runs_dir).join(format!(
        "{name}-{critic}-eta{}-s{}",
        cfg.learner.cvar_eta, cfg.runner.seed
    ))
}
