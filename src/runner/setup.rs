//! A run's set-up: a fresh start from its config, or a resume from its newest
//! usable checkpoint; under MPI, rank 0's choice, config and parameters on
//! every rank.

use std::path::PathBuf;

use anyhow::{Context, Result};

use super::checkpoint_kinds::{load_policy_bytes, LoadedPolicy, Progress};
use super::dist::World;
use super::identity::{resumed_identity, RunIdentity};
use super::job::broadcast_learner_state;
use super::resume::exact_state;
use super::run_dir::RunDir;
use super::status::ranks_note;
use crate::config::TrainConfig;
use crate::env::ACT_DIM;
use crate::learn::Learner;

/// A run ready to train: its settings, networks and progress.
pub(super) struct Opened {
    pub cfg: TrainConfig,
    pub learner: Learner,
    pub progress: Progress,
    /// The checkpoint it resumed from (none: iteration 0).
    pub resumed_from: Option<PathBuf>,
    /// This rank's stored runner state when the resume continues bit-identically.
    pub exact: Option<Vec<u8>>,
}

/// Opens the run in `dir` (see [`super::train::train_in`]) and writes its
/// `config.toml` (rank 0).
pub(super) fn open_run(
    world: &World,
    dir: &RunDir,
    cfg: TrainConfig,
    resume: bool,
) -> Result<Opened> {
    let (cfg, path, resumed) = find_resume_point(world, dir, cfg, resume)?;
    let identity = match (&resumed, world.is_root()) {
        (Some(loaded), true) => Some(checked_identity(dir, loaded, &path, &cfg)?),
        _ => None,
    };
    let exact = resumed
        .as_ref()
        .and_then(|loaded| exact_or_note(world, loaded, &path));
    if let Some(loaded) = resumed
        .as_ref()
        .filter(|_| world.is_root() && exact.is_some())
    {
        note_thread_change(loaded, &cfg, &path);
    }
    let resumed_from = resumed.is_some().then(|| path.clone());
    let (mut cfg, mut learner, mut progress) = match resumed {
        Some(loaded) => resumed_state(world, dir, loaded, &cfg, &path)?,
        None => fresh_state(world, dir, cfg)?,
    };
    if world.is_root() && cfg.learner.ppo.matmul != crate::learn::mat::Precision::F32 {
        println!(
            "update matmuls in bf16 (f32 sums): {}",
            crate::learn::mat::precision_backend(cfg.learner.ppo.matmul)
        );
    }
    if world.size() > 1 {
        let resumed = resumed_from.is_some();
        share_rank_zero_state(world, &mut cfg, &mut learner, &mut progress, resumed)?;
    }
    if world.is_root() {
        let identity = match identity {
            Some(checked) => checked,
            None => identity_of_a_start(dir, &cfg, resume)?,
        };
        identity.write(&dir.root)?;
        progress.identity = Some(identity);
        crate::fsio::write_atomic(&dir.root.join("config.toml"), cfg.to_toml().as_bytes())?;
    }
    Ok(Opened {
        cfg,
        learner,
        progress,
        resumed_from,
        exact,
    })
}

/// The identity the run resumed from `loaded` (at `path`) goes on under;
/// refuses a checkpoint of another run than the directory's.
fn checked_identity(
    dir: &RunDir,
    loaded: &LoadedPolicy,
    path: &std::path::Path,
    cfg: &TrainConfig,
) -> Result<RunIdentity> {
    let stored = RunIdentity::read(&dir.root)?;
    resumed_identity(
        &dir.root,
        stored,
        loaded.progress.identity.as_ref(),
        path,
        cfg,
    )
}

/// The identity of a run starting at iteration 0: the directory's own when a
/// run stopped before its first checkpoint starts again, else a new one.
fn identity_of_a_start(dir: &RunDir, cfg: &TrainConfig, resume: bool) -> Result<RunIdentity> {
    let stored = match resume {
        true => RunIdentity::read(&dir.root)?,
        false => None,
    };
    Ok(stored.unwrap_or_else(|| RunIdentity::new(cfg)))
}

/// Rank 0 picks and loads the checkpoint (none: the run starts again) and
/// sends its bytes to the other ranks. Returns the config to start from (a run
/// stopped before its first checkpoint: its stored one), the checkpoint's path
/// and what it holds.
fn find_resume_point(
    world: &World,
    dir: &RunDir,
    mut cfg: TrainConfig,
    resume: bool,
) -> Result<(TrainConfig, PathBuf, Option<LoadedPolicy>)> {
    let (mut path, mut resumed) = (PathBuf::new(), None);
    if resume && world.is_root() {
        match dir.resume_point_noting() {
            Ok((p, loaded)) => (path, resumed) = (p, Some(loaded)),
            // stopped before its first checkpoint: start it again from its config
            Err(e) => {
                let Some(stored) = dir.config_before_first_checkpoint()? else {
                    return Err(e);
                };
                println!(
                    "{} was stopped before its first checkpoint: starting it again from its config.toml",
                    dir.root.display()
                );
                cfg = keep_runner_settings(stored, &cfg, 0)?;
            }
        }
    }
    if resume && world.size() > 1 {
        // the other ranks load the same file's bytes (empty: no checkpoint)
        let mut bytes = match &resumed {
            Some(_) => std::fs::read(&path)
                .with_context(|| format!("reading checkpoint {}", path.display()))?,
            None => Vec::new(),
        };
        world.broadcast_bytes(&mut bytes);
        if !world.is_root() && !bytes.is_empty() {
            path = PathBuf::from("<rank 0's checkpoint>");
            resumed = Some(load_policy_bytes(&bytes, &path)?);
        }
    }
    Ok((cfg, path, resumed))
}

/// This rank's stored runner state if the checkpoint resumes bit-identically
/// with this job's ranks; otherwise rank 0 says why not.
fn exact_or_note(world: &World, loaded: &LoadedPolicy, path: &std::path::Path) -> Option<Vec<u8>> {
    match exact_state(&loaded.progress, loaded.exact, world.rank(), world.size()) {
        Ok(state) => Some(state),
        Err(why) => {
            if world.is_root() {
                eprintln!(
                    "note: {} resumes, but not bit-identically to an uninterrupted run: {why}",
                    path.display()
                );
            }
            None
        }
    }
}

/// Says that another thread count sums the update's shards in another order.
fn note_thread_change(loaded: &LoadedPolicy, cfg: &TrainConfig, path: &std::path::Path) {
    let (then, now) = (loaded.config.runner.threads, cfg.runner.threads);
    if then != now {
        eprintln!(
            "note: {} was trained with runner.threads = {then}, this resume uses {now}: the update sums its shards in another order, so the run is not bit-identical to an uninterrupted one",
            path.display()
        );
    }
}

/// The stored config (with this invocation's runner settings), networks and
/// progress of the checkpoint at `path`.
fn resumed_state(
    world: &World,
    dir: &RunDir,
    loaded: LoadedPolicy,
    cfg: &TrainConfig,
    path: &std::path::Path,
) -> Result<(TrainConfig, Learner, Progress)> {
    let stored = keep_runner_settings(loaded.config, cfg, loaded.progress.iteration)
        .with_context(|| format!("resuming from {}", path.display()))?;
    check_iterations_left(&stored, loaded.progress.iteration, path)?;
    if world.is_root() {
        println!(
            "resuming {} from {} at iteration {} (lr {:.2e}); {} envs x {} steps{}, {}, seed {}",
            dir.root.display(),
            path.display(),
            loaded.progress.iteration,
            loaded.learner.learning_rate(),
            stored.runner.num_envs,
            stored.runner.steps_per_env,
            ranks_note(world.size()),
            stored.learner.risk_label(),
            stored.runner.seed
        );
    }
    Ok((stored, loaded.learner, loaded.progress))
}

/// Refuses a resume that would train nothing: a run (other than RMA's, whose
/// phase 2 follows its phase-1 target) at or past its target.
fn check_iterations_left(
    stored: &TrainConfig,
    iteration: usize,
    path: &std::path::Path,
) -> Result<()> {
    let target = stored.runner.iterations;
    anyhow::ensure!(
        stored.learner.adaptation.is_some() || iteration < target,
        "{} is at iteration {iteration} and the run's target is {target}: there is nothing to train; pass --iterations N with N above {iteration} to train on",
        path.display()
    );
    Ok(())
}

/// A validated `cfg` with the networks and progress of its iteration 0.
fn fresh_state(
    world: &World,
    dir: &RunDir,
    cfg: TrainConfig,
) -> Result<(TrainConfig, Learner, Progress)> {
    cfg.validate()?;
    if world.is_root() {
        println!(
            "training {} envs x {} steps{}, critic {:?}, {}, seed {} -> {}",
            cfg.runner.num_envs,
            cfg.runner.steps_per_env,
            ranks_note(world.size()),
            cfg.learner.critic,
            cfg.learner.risk_label(),
            cfg.runner.seed,
            dir.root.display()
        );
    }
    let (learner, progress) = fresh_start(&cfg)?;
    Ok((cfg, learner, progress))
}

/// Rank 0's settings (runner overrides included) and parameters on every rank.
fn share_rank_zero_state(
    world: &World,
    cfg: &mut TrainConfig,
    learner: &mut Learner,
    progress: &mut Progress,
    resumed: bool,
) -> Result<()> {
    let mut toml = cfg.to_toml().into_bytes();
    world.broadcast_bytes(&mut toml);
    *cfg = TrainConfig::from_toml_str(&String::from_utf8_lossy(&toml))
        .context("the config broadcast by rank 0")?;
    if !resumed && !world.is_root() {
        // networks of rank 0's config (a restarted run's stored one)
        (*learner, *progress) = fresh_start(cfg)?;
    }
    broadcast_learner_state(world, learner)?;
    if cfg.learner.adaptation.is_some() && world.is_root() {
        println!("note: RMA phase 2 (the adaptation module) runs in one process: after phase 1, resume the run without mpirun");
    }
    Ok(())
}

/// The networks and runner state of a run's iteration 0.
fn fresh_start(cfg: &TrainConfig) -> Result<(Learner, Progress)> {
    let learner = Learner::with_layout(
        &cfg.env.obs_layout(),
        ACT_DIM,
        &cfg.learner,
        cfg.runner.seed,
    )?;
    let progress = Progress {
        rng_seed: cfg.runner.seed ^ 0xA11_0C47,
        ..Default::default()
    };
    Ok((learner, progress))
}

/// A stored run config with this invocation's runner settings, the ones that
/// do not change what is learned (they may differ on resume), and this
/// invocation's last stage if the run had none and is at most at its iteration.
/// Refuses what a resume cannot do (see [`check_phase_one_budget`]).
pub fn keep_runner_settings(
    mut stored: TrainConfig,
    now: &TrainConfig,
    iteration: usize,
) -> Result<TrainConfig> {
    // a last stage added to a run that had none and has not passed it
    stored
        .runner
        .add_action_std_reset(now.runner.action_std_reset, iteration)?;
    check_phase_one_budget(&stored, now.runner.iterations, iteration)?;
    stored.runner.iterations = now.runner.iterations;
    stored.runner.threads = now.runner.threads;
    stored.runner.save_interval = now.runner.save_interval;
    stored.runner.log_interval = now.runner.log_interval;
    Ok(stored)
}

/// RMA's phase 1 (PPO) cannot go on once phase 2 has started: the checkpoint
/// then holds the student, not the teacher. A run past its phase-1 end may not
/// be given another phase-1 budget.
fn check_phase_one_budget(
    stored: &TrainConfig,
    new_iterations: usize,
    iteration: usize,
) -> Result<()> {
    let phase_one_end = stored.runner.iterations;
    if stored.learner.adaptation.is_some()
        && iteration > phase_one_end
        && new_iterations != phase_one_end
    {
        anyhow::bail!(
            "this RMA run is in phase 2 (iteration {iteration}; its phase 1 ended at \
             {phase_one_end}), so its phase-1 budget cannot become {new_iterations}: \
             phase 1 cannot go on from the student. Keep --iterations {phase_one_end}, \
             or move the run's directory away and train it again"
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rma_phase_one_budget_is_fixed_once_phase_two_started() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/rma.toml");
        let mut rma = TrainConfig::from_toml_file(&path).unwrap();
        rma.runner.iterations = 3300;
        // phase 1 (at or before its end) may be given a longer budget
        check_phase_one_budget(&rma, 4000, 3300).unwrap();
        check_phase_one_budget(&rma, 4000, 1200).unwrap();
        // in phase 2 only the same budget resumes
        check_phase_one_budget(&rma, 3300, 3800).unwrap();
        let e = format!(
            "{:#}",
            check_phase_one_budget(&rma, 4000, 3800).unwrap_err()
        );
        assert!(
            e.contains("phase 2") && e.contains("3300") && e.contains("4000"),
            "{e}"
        );
        // a PPO run has no phase 2: any budget
        let mut ppo = rma.clone();
        ppo.learner.adaptation = None;
        check_phase_one_budget(&ppo, 4000, 3800).unwrap();
    }
}
