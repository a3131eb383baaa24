//! RMA phase 2 in the training run: after the teacher's PPO iterations, the
//! adaptation module learns to regress the teacher's latent from the history,
//! on rollouts its own estimate drives through the frozen base policy (the
//! student's deterministic actions). Logged to `adaptation.csv`; checkpoints
//! as in phase 1, marked `latent_source = adaptation`.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use std::sync::Arc;

use anyhow::{bail, Context, Result};
use indicatif::ProgressBar;

use super::metrics::{EpisodeStats, MetricsCsv};
use super::resume::encode_rank_state;
use super::run_dir::{save_both, RunDir, RunLock};
use super::status::log_line;
use super::Progress;
use crate::config::TrainConfig;
use crate::env::{ObsGroup, Scene, VecEnv, ACT_DIM};
use crate::learn::{LatentSource, Learner};

/// Columns of `adaptation.csv`.
pub const ADAPTATION_HEADER: &str = "iteration,wall_s,total_env_steps,collect_s,learn_s,latent_mse_before,latent_mse,episodes,mean_return,lin_tracking_score,fall_fraction,terrain_level";

/// What phase 2 needs to rebuild the envs with a wider observation: the
/// scene (model and terrain), the env threads and the env seed. Not the MPI
/// [`super::World`]: phase 2 runs in one process.
pub(super) struct EnvRebuildInputs<'a> {
    pub scene: &'a Scene,
    pub threads: usize,
    pub env_seed: u64,
}

/// Phase 1 runs without the history (no network reads it, and 50 steps of it
/// would multiply the rollout's width by 30); phase 2 adds it to the
/// observation: the envs are rebuilt on the same terrain and curriculum levels,
/// and the learner gains its adaptation module, everything else carried over.
fn add_history(
    dir: &RunDir,
    cfg: &mut TrainConfig,
    learner: &mut Learner,
    envs: &mut VecEnv,
    obs: &mut Vec<f32>,
    rebuild: &EnvRebuildInputs,
) -> Result<()> {
    let mut next = cfg.clone();
    next.env.observation.groups.push(ObsGroup::History);
    next.validate()?;
    let mut grown = Learner::with_layout(
        &next.env.obs_layout(),
        ACT_DIM,
        &next.learner,
        next.runner.seed,
    )?;
    grown
        .load_state_keeping(&learner.state(), |name| name.contains("adapt"))
        .context("carrying the teacher into phase 2")?;
    let mut venv = VecEnv::new(
        Arc::new(next.env.clone()),
        &rebuild.scene.model,
        rebuild.scene.terrain.clone(),
        next.runner.num_envs,
        rebuild.threads,
        rebuild.env_seed ^ 0xADA9,
    )?;
    // phase 1's live levels (a checkpoint's stored ones may hold every MPI rank's)
    if let Some(levels) = envs.terrain_levels() {
        venv.restore_terrain_levels(&levels)
            .context("restoring the terrain curriculum for phase 2")?;
    }
    *obs = venv.batch().obs.clone();
    *envs = venv;
    *learner = grown;
    *cfg = next;
    crate::fsio::write_atomic(&dir.root.join("config.toml"), cfg.to_toml().as_bytes())?;
    Ok(())
}

/// Runs phase 2 from `progress.iteration` up to `phase1_end + adaptation.iterations`.
/// Returns whether it was interrupted, and the last checkpoint written (if any).
#[allow(clippy::too_many_arguments)]
pub(super) fn adaptation_phase(
    dir: &RunDir,
    cfg: &mut TrainConfig,
    learner: &mut Learner,
    progress: &mut Progress,
    envs: &mut VecEnv,
    obs: &mut Vec<f32>,
    rebuild: &EnvRebuildInputs,
    stop: &AtomicBool,
    bar: &ProgressBar,
) -> Result<(bool, Option<PathBuf>)> {
    let Some(a) = cfg.learner.adaptation.clone() else {
        return Ok((false, None));
    };
    let end = cfg.runner.iterations + a.iterations;
    if progress.iteration >= end {
        return Ok((false, None));
    }
    if cfg.env.obs_layout().range(&a.input).is_none() {
        add_history(dir, cfg, learner, envs, obs, rebuild)?;
    }
    let r = &cfg.runner;
    let cfg = &*cfg;
    learner.set_latent_source(LatentSource::Adaptation);
    log_line(
        bar,
        format!(
            "RMA phase 2: adaptation module from iteration {} to {end} (teacher frozen)",
            progress.iteration
        ),
    );
    bar.set_length(end as u64);
    let mut csv = MetricsCsv::open_resumed_with(
        &dir.root.join("adaptation.csv"),
        progress.iteration,
        ADAPTATION_HEADER,
    )?;
    let width = envs.obs_width();
    let rows = r.num_envs * r.steps_per_env;
    let mut buffer = Vec::with_capacity(rows * width);
    let lin_weight_dt = cfg.env.reward.lin_vel_tracking * cfg.env.control.policy_dt_s();
    let wall_start = Instant::now() - std::time::Duration::from_secs_f64(progress.wall_s);
    let mut last = None;
    let mut episodes = Vec::new();
    while progress.iteration < end {
        if stop.load(Ordering::SeqCst) {
            let path = save_phase_two(dir, learner, cfg, progress, envs, obs)?;
            log_line(
                bar,
                format!(
                    "interrupted: checkpoint written at iteration {}",
                    progress.iteration
                ),
            );
            return Ok((true, Some(path)));
        }
        let t0 = Instant::now();
        buffer.clear();
        for _ in 0..r.steps_per_env {
            buffer.extend_from_slice(obs);
            let actions = learner.act_mean(obs);
            let b = envs.step(&actions);
            obs.copy_from_slice(&b.obs);
            episodes.extend(envs.drain_episodes());
        }
        let collect_s = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let reg = learner.regress_latent(&buffer, rows)?;
        let (before, mse) = (reg.mse_before, reg.mean_minibatch_mse);
        let learn_s = t1.elapsed().as_secs_f64();
        anyhow::ensure!(
            mse.is_finite(),
            "RMA phase 2 diverged at iteration {}: latent MSE {mse}",
            progress.iteration + 1
        );
        progress.iteration += 1;
        progress.total_env_steps += rows as u64;
        progress.wall_s = wall_start.elapsed().as_secs_f64();
        progress.terrain_levels = envs.terrain_levels();
        let stats = EpisodeStats::from_episodes(&episodes, lin_weight_dt);
        let level = envs.mean_terrain_level();
        let times = (collect_s, learn_s);
        csv.write_line(&phase_two_csv_row(
            progress,
            times,
            (before, mse),
            &stats,
            level,
        ))?;
        let status = phase_two_status(progress, times, (before, mse), &stats);
        if progress.iteration.is_multiple_of(r.log_interval) {
            log_line(bar, status.clone());
        }
        bar.set_position(progress.iteration as u64);
        bar.set_message(status);
        if !episodes.is_empty() {
            episodes.clear();
        }
        if progress.iteration.is_multiple_of(r.save_interval) || progress.iteration == end {
            last = Some(save_phase_two(dir, learner, cfg, progress, envs, obs)?);
        }
    }
    Ok((false, last))
}

/// Phase 2's checkpoints (its envs' episodes stored for an exact resume).
fn save_phase_two(
    dir: &RunDir,
    learner: &Learner,
    cfg: &TrainConfig,
    progress: &mut Progress,
    envs: &VecEnv,
    obs: &[f32],
) -> Result<PathBuf> {
    progress.rank_states = vec![encode_rank_state(envs, obs, &EpisodeStats::default(), None)];
    save_both(dir, learner, cfg, progress)
}

/// One line of `adaptation.csv` (see [`ADAPTATION_HEADER`]).
fn phase_two_csv_row(
    progress: &Progress,
    (collect_s, learn_s): (f64, f64),
    (before, mse): (f32, f32),
    stats: &EpisodeStats,
    terrain_level: f64,
) -> String {
    let falls = if stats.episodes > 0 {
        stats.falls as f64 / stats.episodes as f64
    } else {
        0.0
    };
    format!(
        "{},{:.3},{},{:.4},{:.4},{:.6},{:.6},{},{:.5},{:.5},{:.4},{:.3}",
        progress.iteration,
        progress.wall_s,
        progress.total_env_steps,
        collect_s,
        learn_s,
        before,
        mse,
        stats.episodes,
        stats.mean_return,
        stats.lin_tracking_score,
        falls,
        terrain_level
    )
}

/// Phase 2's status line.
fn phase_two_status(
    progress: &Progress,
    (collect_s, learn_s): (f64, f64),
    (before, mse): (f32, f32),
    stats: &EpisodeStats,
) -> String {
    format!(
        "it {:>5} | phase 2 | {:>7.1} min | collect {:.2}s regress {:.2}s | latent mse {:.5} (before {:.5}) | return {:>7.3} | track {:.3} | falls {}/{}",
        progress.iteration,
        progress.wall_s / 60.0,
        collect_s,
        learn_s,
        mse,
        before,
        stats.mean_return,
        stats.lin_tracking_score,
        stats.falls,
        stats.episodes
    )
}

/// Rewinds the RMA run in `dir` to the end of phase 1 so that phase 2 trains again
/// on the frozen teacher: a fresh adaptation module (and optimiser state), the
/// teacher's weights unchanged, progress as `metrics.csv` logged it at phase 1's
/// last iteration. The discarded phase-2 checkpoints are moved (not deleted) to
/// `discarded-adaptation/`; `adaptation.csv` drops its rows when phase 2 resumes.
/// Terrain levels are the checkpoint's (phase 2 moves them a little). Returns the
/// iteration phase 2 restarts from.
pub fn restart_adaptation(dir: &RunDir) -> Result<usize> {
    let _lock = RunLock::acquire(&dir.root)?;
    let (path, loaded) = dir.resume_point()?;
    let cfg = loaded.config;
    if cfg.learner.adaptation.is_none() {
        bail!(
            "{} is not an RMA run: its config has no [learner.adaptation], so it has no phase 2 to restart",
            dir.root.display()
        );
    }
    let phase1_end = cfg.runner.iterations;
    if loaded.progress.iteration <= phase1_end {
        bail!(
            "{} is at iteration {} and its phase 2 starts after {phase1_end}: nothing to restart",
            path.display(),
            loaded.progress.iteration
        );
    }
    let (wall_s, total_env_steps) = metrics_at(&dir.metrics(), phase1_end)?;
    let mut fresh = Learner::with_layout(
        &cfg.env.obs_layout(),
        ACT_DIM,
        &cfg.learner,
        cfg.runner.seed,
    )?;
    let teacher: Vec<_> = loaded
        .learner
        .state()
        .into_iter()
        .filter(|t| !t.name.contains("adapt"))
        .collect();
    fresh
        .load_state_keeping(&teacher, |name| name.contains("adapt"))
        .context("carrying the teacher over")?;
    let progress = Progress {
        iteration: phase1_end,
        total_env_steps,
        wall_s,
        // phase 2's envs are not those of phase 1's end: that resume is not exact
        rank_states: Vec::new(),
        ..loaded.progress
    };
    let discarded = dir.root.join("discarded-adaptation");
    std::fs::create_dir_all(&discarded)
        .with_context(|| format!("creating {}", discarded.display()))?;
    let old = discarded.join(format!(
        "latest-at-{}.safetensors",
        loaded.progress.iteration
    ));
    let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    crate::fsio::write_atomic(&old, &bytes)?;
    for (it, p) in dir.checkpoints_by_iteration() {
        if it > phase1_end {
            let to = discarded.join(p.file_name().context("checkpoint without a name")?);
            std::fs::rename(&p, &to).with_context(|| format!("moving {}", p.display()))?;
        }
    }
    save_both(dir, &fresh, &cfg, &progress)?;
    Ok(phase1_end)
}

/// Makes phase 1's checkpoint `teacher` the frozen teacher of the RMA run in `dir`,
/// which must stand at the end of its phase 1 (phase 2 not started): its
/// `latest.safetensors` gets the chosen checkpoint's networks (and optimiser
/// state) with the run's own progress, so phase 2 starts from where phase 1
/// stopped, on the chosen teacher. The numbered checkpoints stay as they were
/// trained. Installing the same teacher twice changes nothing.
pub fn install_teacher(dir: &RunDir, teacher: &std::path::Path) -> Result<()> {
    let _lock = RunLock::acquire(&dir.root)?;
    let (path, run) = dir.resume_point()?;
    let Some(_) = run.config.learner.adaptation else {
        bail!(
            "{} is not an RMA run: its config has no [learner.adaptation], so it has no teacher to choose",
            dir.root.display()
        );
    };
    let phase1_end = run.config.runner.iterations;
    if run.progress.iteration != phase1_end {
        bail!(
            "{} is at iteration {}, not at the end of its phase 1 ({phase1_end}): a teacher is chosen between the two phases",
            path.display(),
            run.progress.iteration
        );
    }
    let chosen = crate::runner::load_policy(teacher)
        .with_context(|| format!("loading the chosen teacher {}", teacher.display()))?;
    if chosen.progress.iteration > phase1_end
        || chosen.learner.latent_source() != LatentSource::Encoder
    {
        bail!(
            "{} is not a phase-1 checkpoint of this run (iteration {}, latent from {:?})",
            teacher.display(),
            chosen.progress.iteration,
            chosen.learner.latent_source()
        );
    }
    if chosen.config.learner != run.config.learner || chosen.config.env != run.config.env {
        bail!(
            "{} was trained with another learner or env config than {}",
            teacher.display(),
            dir.root.display()
        );
    }
    crate::runner::save_policy(&dir.latest(), &chosen.learner, &run.config, &run.progress)
}

/// `wall_s` and `total_env_steps` of `metrics.csv`'s row for `iteration`.
fn metrics_at(path: &std::path::Path, iteration: usize) -> Result<(f64, u64)> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let rows =
        super::metrics::metrics_columns(&text, path, ["iteration", "wall_s", "total_env_steps"])?;
    for [it, wall, steps] in rows {
        if it.parse::<usize>().ok() == Some(iteration) {
            let wall_s = wall.parse().with_context(|| {
                format!(
                    "{}: bad wall_s in the row of iteration {iteration}",
                    path.display()
                )
            })?;
            let steps = steps.parse().with_context(|| {
                format!(
                    "{}: bad total_env_steps in the row of iteration {iteration}",
                    path.display()
                )
            })?;
            return Ok((wall_s, steps));
        }
    }
    bail!(
        "{} has no row for iteration {iteration} (the end of phase 1)",
        path.display()
    )
}
