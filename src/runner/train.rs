//! The training loop: collect `steps_per_env` steps from every env, update,
//! log, checkpoint. Resumable; Ctrl-C writes a last checkpoint.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::metrics::{CollectTimes, EpisodeStats, IterationRow, MetricsCsv};
use super::policy_file::{load_policy, save_policy, Progress};
use crate::config::TrainConfig;
use crate::env::risk::NUM_RISK_TERMS;
use crate::env::{build_scene, EpisodeSummary, VecEnv, ACT_DIM, OBS_DIM};
use crate::learn::{Learner, Rollout, UpdateStats, UpdateTimes};

/// Name of the rolling checkpoint in a run directory.
pub const LATEST: &str = "latest.safetensors";

/// Where a run keeps its files.
pub struct RunDir {
    pub root: PathBuf,
}

impl RunDir {
    pub fn latest(&self) -> PathBuf {
        self.root.join(LATEST)
    }
    pub fn checkpoint(&self, iteration: usize) -> PathBuf {
        self.root
            .join("checkpoints")
            .join(format!("model_{iteration:06}.safetensors"))
    }
    pub fn metrics(&self) -> PathBuf {
        self.root.join("metrics.csv")
    }
}

/// Called once per iteration with the row just logged (for the rerun logger, tests).
pub trait IterationObserver {
    fn on_iteration(&mut self, _row: &IterationRow, _learner: &Learner) -> Result<()> {
        Ok(())
    }
}

impl IterationObserver for () {}

/// What a finished (or interrupted) run reports.
#[derive(Debug, Clone)]
pub struct TrainSummary {
    pub run_dir: PathBuf,
    pub iterations_done: usize,
    pub interrupted: bool,
    pub last_checkpoint: PathBuf,
    pub final_episode_stats: EpisodeStats,
}

/// Starts a new run in `run_dir`, or resumes the one there when `resume` is set
/// (then `cfg` only supplies a new iteration target).
pub fn train(
    cfg: TrainConfig,
    run_dir: &Path,
    resume: bool,
    stop: Arc<AtomicBool>,
    observer: &mut dyn IterationObserver,
) -> Result<TrainSummary> {
    let dir = RunDir {
        root: run_dir.to_path_buf(),
    };
    std::fs::create_dir_all(&dir.root)
        .with_context(|| format!("creating run directory {}", dir.root.display()))?;
    let (cfg, mut learner, mut progress) = if resume {
        let latest = dir.latest();
        let loaded =
            load_policy(&latest).with_context(|| format!("resuming from {}", latest.display()))?;
        let mut stored = loaded.config;
        stored.runner.iterations = cfg.runner.iterations;
        println!(
            "resuming {} at iteration {} (lr {:.2e})",
            dir.root.display(),
            loaded.progress.iteration,
            loaded.learner.learning_rate()
        );
        (stored, loaded.learner, loaded.progress)
    } else {
        let learner = Learner::new(OBS_DIM, ACT_DIM, &cfg.learner, cfg.runner.seed)?;
        let progress = Progress {
            rng_seed: cfg.runner.seed ^ 0xA11_0C47,
            ..Default::default()
        };
        (cfg, learner, progress)
    };
    std::fs::write(dir.root.join("config.toml"), cfg.to_toml()).context("writing config.toml")?;

    let r = &cfg.runner;
    let threads = crate::config::worker_threads(r.threads);
    // Envs restart fresh episodes on resume, seeded by the iteration so a resumed
    // run does not replay the first run's episodes.
    let env_seed = r.seed.wrapping_add(progress.iteration as u64 * 0x9E37_79B9);
    let scene = build_scene(&cfg.env, r.seed).context("building the scene")?;
    let mut envs = VecEnv::new(
        Arc::new(cfg.env.clone()),
        &scene.model,
        scene.terrain.clone(),
        r.num_envs,
        threads,
        env_seed,
    )?;
    if cfg.env.episode.randomize_initial_length {
        envs.randomize_episode_progress();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(progress.rng_seed);
    rng.set_word_pos(progress.rng_word_pos);
    let mut rollout = Rollout::new(r.steps_per_env, r.num_envs, OBS_DIM, ACT_DIM);
    let mut metrics = MetricsCsv::open(&dir.metrics())?;
    let lin_weight_dt = cfg.env.reward.lin_vel_tracking * cfg.env.control.policy_dt_s();

    let bar = progress_bar(progress.iteration, r.iterations);
    let mut obs = envs.batch().obs.clone();
    let mut episodes: Vec<EpisodeSummary> = Vec::with_capacity(r.num_envs * 4);
    let mut last_stats = EpisodeStats::default();
    let mut interrupted = false;
    let mut last_checkpoint = dir.latest();
    let wall_start = Instant::now() - std::time::Duration::from_secs_f64(progress.wall_s);

    while progress.iteration < r.iterations {
        if stop.load(Ordering::SeqCst) {
            interrupted = true;
            break;
        }
        // --- collection ---
        let t0 = Instant::now();
        rollout.clear();
        let mut risk_exceeded = [0u64; NUM_RISK_TERMS];
        let mut risk_fired = [0u64; NUM_RISK_TERMS];
        let mut inference_s = 0.0;
        for _ in 0..r.steps_per_env {
            let ti = Instant::now();
            let out = learner.act(&obs, &mut rng);
            inference_s += ti.elapsed().as_secs_f64();
            let b = envs.step(&out.actions);
            for k in 0..NUM_RISK_TERMS {
                risk_exceeded[k] += b.risk_exceeded[k];
                risk_fired[k] += b.risk_fired[k];
            }
            rollout.push(&obs, &out, &b.rewards, &b.dones, &b.time_outs, &b.final_obs)?;
            obs.copy_from_slice(&b.obs);
            episodes.extend(envs.drain_episodes());
        }
        rollout.set_last_obs(&obs)?;
        let collect_s = t0.elapsed().as_secs_f64();
        let step_times = envs.take_times();
        let collect_times = CollectTimes {
            physics_s: step_times.physics_s,
            task_s: step_times.task_s,
            reset_s: step_times.reset_s,
            inference_s,
            storage_s: (collect_s
                - inference_s
                - step_times.physics_s
                - step_times.task_s
                - step_times.reset_s)
                .max(0.0),
        };
        // --- learning ---
        let t1 = Instant::now();
        let update: UpdateStats = learner.update(&rollout)?;
        let learn_s = t1.elapsed().as_secs_f64();

        progress.iteration += 1;
        let iteration_env_steps = (r.num_envs * r.steps_per_env) as u64;
        progress.total_env_steps += iteration_env_steps;
        progress.wall_s = wall_start.elapsed().as_secs_f64();
        progress.rng_word_pos = rng.get_word_pos();
        if !episodes.is_empty() {
            last_stats = EpisodeStats::from_episodes(&episodes, lin_weight_dt);
        }
        let row = IterationRow {
            iteration: progress.iteration,
            wall_s: progress.wall_s,
            total_env_steps: progress.total_env_steps,
            iteration_env_steps,
            collect_s,
            learn_s,
            collect_times,
            episodes: &last_stats,
            update: &update,
            terrain_level: envs.mean_terrain_level(),
            risk_exceeded: &risk_exceeded,
            risk_fired: &risk_fired,
            instabilities: envs.instabilities(),
        };
        metrics.write(&row)?;
        observer.on_iteration(&row, &learner)?;
        bar.set_position(progress.iteration as u64);
        let status = format!(
            "it {:>5} | {:>7.1} min | {:>6.0} steps/s | collect {:.2}s learn {:.2}s | return {:>7.3} | len {:>5.0} | track {:.3} | falls {:>3}/{:<3} | level {:.2} | risk {}/{} | lr {:.1e} | std {:.3} | value loss {:.4}",
            progress.iteration,
            progress.wall_s / 60.0,
            iteration_env_steps as f64 / (collect_s + learn_s),
            collect_s,
            learn_s,
            last_stats.mean_return,
            last_stats.mean_length_steps,
            last_stats.lin_tracking_score,
            last_stats.falls,
            last_stats.episodes,
            row.terrain_level,
            risk_fired.iter().sum::<u64>(),
            risk_exceeded.iter().sum::<u64>(),
            update.learning_rate,
            update.mean_std,
            update.value_loss,
        );
        if progress.iteration.is_multiple_of(r.log_interval) || progress.iteration == 1 {
            log_line(&bar, status.clone());
            log_line(&bar, time_split(&collect_times, &update.time));
        }
        bar.set_message(status);
        episodes.clear();
        if progress.iteration % r.save_interval == 0 || progress.iteration == r.iterations {
            last_checkpoint = save_both(&dir, &learner, &cfg, &progress)?;
        }
    }
    if interrupted {
        last_checkpoint = save_both(&dir, &learner, &cfg, &progress)?;
        log_line(
            &bar,
            format!(
                "interrupted: checkpoint written at iteration {}",
                progress.iteration
            ),
        );
    }
    bar.finish_and_clear();
    Ok(TrainSummary {
        run_dir: dir.root.clone(),
        iterations_done: progress.iteration,
        interrupted,
        last_checkpoint,
        final_episode_stats: last_stats,
    })
}

/// Writes the numbered checkpoint and the rolling `latest` one.
fn save_both(
    dir: &RunDir,
    learner: &Learner,
    cfg: &TrainConfig,
    progress: &Progress,
) -> Result<PathBuf> {
    let numbered = dir.checkpoint(progress.iteration);
    save_policy(&numbered, learner, cfg, progress)?;
    save_policy(&dir.latest(), learner, cfg, progress)?;
    Ok(numbered)
}

/// One log line saying where the iteration's time went.
fn time_split(c: &CollectTimes, l: &UpdateTimes) -> String {
    format!(
        "      time | collect: physics {:.3}s task {:.3}s reset {:.3}s inference {:.3}s storage {:.3}s | learn: targets {:.3}s gather {:.3}s forward {:.3}s loss {:.3}s backward {:.3}s clip {:.3}s adam {:.3}s",
        c.physics_s,
        c.task_s,
        c.reset_s,
        c.inference_s,
        c.storage_s,
        l.targets_s,
        l.gather_s,
        l.forward_s,
        l.loss_s,
        l.backward_s,
        l.clip_s,
        l.adam_s
    )
}

/// Prints above the bar on a terminal, plainly otherwise (logs of background runs).
fn log_line(bar: &ProgressBar, line: String) {
    if bar.is_hidden() {
        println!("{line}");
    } else {
        bar.println(line);
    }
}

fn progress_bar(start: usize, end: usize) -> ProgressBar {
    let bar = ProgressBar::new(end as u64);
    bar.set_position(start as u64);
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] it {pos}/{len} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar
}
