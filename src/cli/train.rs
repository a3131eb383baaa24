//! `rall train`: start or resume a training run.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;
use nix::sys::signal::{SigSet, Signal};

use crate::config::{ActionStdReset, TrainConfig};
use crate::learn::CriticKind;
use crate::runner::run_dir::check_new_run_folder;
use crate::runner::{
    restart_adaptation, train_in, IterationObserver, PhaseOneOnly, RunDir, World, LATEST,
};
use crate::viz::{RerunTarget, TrainRecorder, TrainRecordingOptions};

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Run configuration (TOML with [env], [learner], [runner]); see configs/.
    /// [default: configs/flat.toml]. A resumed run keeps the config it was started with.
    #[arg(long, conflicts_with = "resume")]
    pub config: Option<PathBuf>,
    /// CVaR level eta of the actor's objective (0.5 = RALL, 1 = risk neutral).
    #[arg(long, conflicts_with = "resume")]
    pub cvar_eta: Option<f32>,
    /// Critic: iqn (value distribution) or scalar (risk-neutral baseline).
    #[arg(long, value_parser = parse_critic, conflicts_with = "resume")]
    pub critic: Option<CriticKind>,
    #[arg(long, conflicts_with = "resume")]
    pub seed: Option<u64>,
    /// Parallel environments.
    #[arg(long, conflicts_with = "resume")]
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
    /// A last stage: after iteration IT, set the action std to STD and train on
    /// (`runner.action_std_reset`). With --resume, it can be added to a run that has
    /// not passed IT.
    #[arg(long, value_name = "IT:STD", value_parser = parse_std_reset)]
    pub action_std_reset: Option<ActionStdReset>,
    /// Run directory (default: <runs_dir>/<config name>-<critic>-eta<eta>-s<seed>).
    #[arg(long)]
    pub run_dir: Option<PathBuf>,
    /// Resume the run in this directory from its latest checkpoint.
    #[arg(long, conflicts_with = "run_dir")]
    pub resume: Option<PathBuf>,
    /// Train into a run directory that holds files rall did not write (they are
    /// left alone). A system directory is refused even so.
    #[arg(long, conflicts_with = "resume")]
    pub force: bool,
    /// RMA: discard the run's phase 2 (the adaptation module; its checkpoints are
    /// moved to <run>/discarded-adaptation/) and train it again on the frozen
    /// teacher from the end of phase 1. With a larger --iterations, the teacher
    /// first trains on (the checkpoint keeps its weights and optimiser state; the
    /// episodes start afresh).
    #[arg(long, requires = "resume")]
    pub restart_adaptation: bool,
    /// RMA: stop when phase 1 (the teacher) ends, before phase 2; resuming the run
    /// later trains phase 2 (`rall experiment` chooses the teacher there). No
    /// effect on a run without phase 2.
    #[arg(long)]
    pub stop_after_phase_one: bool,
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
    CriticKind::from_name(s).map_err(|e| e.to_string())
}

/// `rall train`, alone or as one rank under `mpirun`/`srun` (an error on any
/// rank ends the whole job: the other ranks would wait for it forever).
pub fn run(args: &TrainArgs) -> Result<()> {
    // before MPI starts its threads, so that they leave SIGUSR1/2 to the waiter
    block_forwarded_stop_signals()?;
    let world = World::from_env()?;
    match run_in(&world, args) {
        Err(e) if world.size() > 1 => {
            eprintln!("error on rank {} of {}: {e:#}", world.rank(), world.size());
            world.abort(1)
        }
        other => other,
    }
}

fn run_in(world: &World, args: &TrainArgs) -> Result<()> {
    let (cfg, run_dir, resume) = match (&args.resume, &args.run_dir) {
        // rank 0 reads the run's checkpoint and broadcasts it (`train_in`)
        (Some(dir), _) if !world.is_root() => (TrainConfig::default(), dir.clone(), true),
        (Some(dir), _) => (resumed_config(dir, args)?, dir.clone(), true),
        (None, run_dir) => {
            let (cfg, run_dir) = new_run_config(world, run_dir.as_ref(), args)?;
            (cfg, run_dir, false)
        }
    };
    let stop = install_stop_handler()?;
    let target = RerunTarget::from_flags(
        args.rerun_save.as_deref(),
        args.rerun_spawn,
        args.rerun_connect.as_deref(),
    );
    let phase_one_only = args.stop_after_phase_one;
    let observed = |observer: &mut dyn IterationObserver, cfg, stop| {
        if phase_one_only {
            train_in(
                world,
                cfg,
                &run_dir,
                resume,
                stop,
                &mut PhaseOneOnly(observer),
            )
        } else {
            train_in(world, cfg, &run_dir, resume, stop, observer)
        }
    };
    let summary = match target.filter(|_| world.is_root()) {
        None => observed(&mut (), cfg, stop)?,
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
            let summary = observed(&mut recorder, cfg, stop)?;
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
    if !world.is_root() {
        return Ok(());
    }
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

/// The config a resumed run continues with: the one it was started with, with
/// this invocation's runner settings (and RMA's phase 2 restarted if asked).
fn resumed_config(dir: &Path, args: &TrainArgs) -> Result<TrainConfig> {
    // what the run was started with; only runner settings may change
    let run = RunDir {
        root: dir.to_path_buf(),
    };
    if args.restart_adaptation {
        let from = restart_adaptation(&run)?;
        let next = match args.iterations {
            Some(n) if n > from => {
                format!("the teacher trains on from iteration {from} to {n} (phase 1), then phase 2 starts afresh")
            }
            _ => format!("phase 2 restarts from iteration {from} on the frozen teacher"),
        };
        eprintln!(
            "{}: {next} (the discarded checkpoints are in discarded-adaptation/)",
            dir.display()
        );
    }
    let mut cfg = match run.resume_point() {
        Ok((_, loaded)) => loaded.config,
        // stopped before its first checkpoint: `train` starts it again
        Err(e) => run
            .config_before_first_checkpoint()?
            .ok_or(e)
            .with_context(|| format!("cannot resume {}", dir.display()))?,
    };
    apply_runner_overrides(&mut cfg, args);
    if let Some(reset) = args.action_std_reset {
        match cfg.runner.action_std_reset {
            Some(had) if had != reset => bail!(
                "{} already resets the action std after iteration {} (to {}): a run has one such stage",
                dir.display(),
                had.after_iteration,
                had.action_std
            ),
            _ => cfg.runner.action_std_reset = Some(reset),
        }
    }
    cfg.validate().context("after command-line overrides")?;
    Ok(cfg)
}

/// A new run's config (the file and the command-line overrides) and its directory,
/// refused when that directory already holds a run.
fn new_run_config(
    world: &World,
    run_dir: Option<&PathBuf>,
    args: &TrainArgs,
) -> Result<(TrainConfig, PathBuf)> {
    let config = args
        .config
        .clone()
        .unwrap_or_else(|| PathBuf::from("configs/flat.toml"));
    let mut cfg = TrainConfig::from_toml_file(&config)?;
    apply_run_overrides(&mut cfg, args);
    apply_runner_overrides(&mut cfg, args);
    if let Some(reset) = args.action_std_reset {
        cfg.runner.action_std_reset = Some(reset);
    }
    cfg.validate().context("after command-line overrides")?;
    let run_dir = run_dir
        .cloned()
        .unwrap_or_else(|| default_run_dir(&config, &cfg));
    if world.is_root() {
        let taken = run_dir.join(LATEST).exists() || run_dir.join("metrics.csv").exists();
        if taken {
            bail!(
                "{} already holds a run; pass --resume {} to continue it or choose another --run-dir",
                run_dir.display(),
                run_dir.display()
            );
        }
        check_new_run_folder(&run_dir, args.force)?;
    }
    Ok((cfg, run_dir))
}

/// Overrides that define a new run (refused with `--resume` by clap).
fn apply_run_overrides(cfg: &mut TrainConfig, args: &TrainArgs) {
    if let Some(eta) = args.cvar_eta {
        cfg.learner.cvar_eta = Some(eta);
    }
    if let Some(c) = args.critic {
        cfg.learner.critic = c;
        if !c.has_quantiles() && args.cvar_eta.is_none() {
            // a scalar critic has no distribution to distort: the config's
            // risk setting no longer applies (an explicit --cvar-eta is still refused)
            cfg.learner.cvar_eta = None;
            cfg.learner.distortion = None;
        }
    }
    if let Some(s) = args.seed {
        cfg.runner.seed = s;
    }
    if let Some(n) = args.envs {
        cfg.runner.num_envs = n;
    }
}

/// Runner settings that do not change what is learned (also applied on resume).
fn apply_runner_overrides(cfg: &mut TrainConfig, args: &TrainArgs) {
    if let Some(t) = args.threads {
        cfg.runner.threads = t;
    }
    if let Some(k) = args.iterations {
        cfg.runner.iterations = k;
    }
    if let Some(k) = args.save_interval {
        cfg.runner.save_interval = k;
    }
}

fn parse_std_reset(s: &str) -> Result<ActionStdReset, String> {
    let (it, std) = s
        .split_once(':')
        .ok_or_else(|| format!("expected IT:STD (e.g. 3000:0.5), got {s:?}"))?;
    let after_iteration = it
        .trim()
        .parse()
        .map_err(|e| format!("iteration {it:?}: {e}"))?;
    let action_std: f32 = std
        .trim()
        .parse()
        .map_err(|e| format!("action std {std:?}: {e}"))?;
    if !(action_std.is_finite() && action_std > 0.0) {
        return Err(format!("the action std must be positive, got {action_std}"));
    }
    Ok(ActionStdReset {
        after_iteration,
        action_std,
    })
}

fn default_run_dir(config: &std::path::Path, cfg: &TrainConfig) -> PathBuf {
    let name = config.file_stem().and_then(|s| s.to_str()).unwrap_or("run");
    // a critic without quantiles is named by the risk label already
    let critic = match cfg.learner.critic {
        c if c.has_quantiles() => format!("{c}-"),
        _ => String::new(),
    };
    PathBuf::from(&cfg.runner.runs_dir).join(format!(
        "{name}-{critic}{}-s{}",
        cfg.learner.risk_label(),
        cfg.runner.seed
    ))
}

/// Signals that stop a run as SIGTERM does and that `mpirun` forwards to every
/// rank without aborting the job. Open MPI's `mpirun` turns a SIGTERM, SIGINT
/// or SIGHUP of its own into exit status 1 whatever the ranks do, and kills
/// them a second later (`odls_base_sigkill_timeout`); SIGUSR1 and SIGUSR2 it
/// passes on, and exits with the ranks' status.
const FORWARDED_STOP_SIGNALS: [Signal; 2] = [Signal::SIGUSR1, Signal::SIGUSR2];

fn forwarded_stop_signals() -> SigSet {
    let mut set = SigSet::empty();
    for s in FORWARDED_STOP_SIGNALS {
        set.add(s);
    }
    set
}

/// Blocks SIGUSR1 and SIGUSR2 in this thread and in every thread started from
/// it afterwards, so that only the waiter of [`install_stop_handler`] takes
/// them. Call it before anything starts threads (MPI's initialisation does).
pub fn block_forwarded_stop_signals() -> Result<()> {
    forwarded_stop_signals()
        .thread_block()
        .context("blocking SIGUSR1 and SIGUSR2 for the stop handler")
}

/// One stop request: the first asks the run to finish its iteration and write
/// a checkpoint; another more than a second later exits at once.
struct StopRequests {
    stop: Arc<AtomicBool>,
    first: std::sync::OnceLock<std::time::Instant>,
}

impl StopRequests {
    fn request(&self) {
        let t0 = *self.first.get_or_init(std::time::Instant::now);
        // A second signal within a second is the same request delivered twice
        // (GNU timeout signals the child and then its process group; mpirun
        // forwards a SIGUSR1 the scheduler also sent to each rank).
        if self.stop.swap(true, Ordering::SeqCst) {
            if t0.elapsed() >= std::time::Duration::from_secs(1) {
                eprintln!("second interrupt: exiting without a checkpoint");
                std::process::exit(130);
            }
            return;
        }
        eprintln!(
            "interrupt (SIGINT/SIGTERM/SIGHUP/SIGUSR1/SIGUSR2): finishing this iteration and writing a checkpoint (interrupt again to abort)"
        );
    }
}

/// A flag set by SIGINT, SIGTERM (what schedulers send), SIGHUP, SIGUSR1 or
/// SIGUSR2 (what to send under `mpirun`, see [`FORWARDED_STOP_SIGNALS`]): the
/// run finishes its iteration and writes a checkpoint. A second signal after
/// more than a second exits at once.
pub fn install_stop_handler() -> Result<Arc<AtomicBool>> {
    let stop = Arc::new(AtomicBool::new(false));
    let requests = Arc::new(StopRequests {
        stop: stop.clone(),
        first: std::sync::OnceLock::new(),
    });
    let on_ctrlc = requests.clone();
    ctrlc::set_handler(move || on_ctrlc.request()).context("installing the interrupt handler")?;
    block_forwarded_stop_signals()?;
    std::thread::Builder::new()
        .name("rall-stop-signals".into())
        .spawn(move || {
            let set = forwarded_stop_signals();
            while set.wait().is_ok() {
                requests.request();
            }
        })
        .context("starting the SIGUSR1/SIGUSR2 waiter")?;
    Ok(stop)
}
