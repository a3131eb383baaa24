//! The training loop: collect `steps_per_env` steps from every env, update,
//! log, checkpoint. Resumable; Ctrl-C writes a last checkpoint.
//!
//! Data-parallel under MPI ([`World`]): every rank runs this loop over its own
//! `num_envs` environments (own seeds, own terrain curriculum) and the update
//! averages the gradients of all ranks, so all hold the same parameters; rank 0
//! alone writes the run directory. Ranks compare a hash of their learner state
//! every [`PARAM_CHECK_INTERVAL`] iterations and at every checkpoint.
//!
//! The set-up (fresh or resumed) is in `setup`, the run directory and its lock
//! in `run_dir`, what crosses ranks in `job`, the status line in `status`, the
//! fault hooks in `faults`, RMA's phase 2 in `adapt`.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::ProgressBar;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::adapt::{adaptation_phase, EnvRebuildInputs};
use super::checkpoint_kinds::Progress;
use super::dist::{rank_seed, World};
use super::faults::FaultHooks;
use super::job::{any_rank_stopped, check_same_state, save_job_checkpoint, JobIteration};
use super::metrics::{CollectTimes, EpisodeStats, IterationRow, MetricsCsv};
use super::resume::start_envs;
use super::setup::{open_run, Opened};
use super::status::{log_line, progress_bar, status_line, time_split};
use crate::config::TrainConfig;
use crate::env::risk::NUM_RISK_TERMS;
use crate::env::{build_scene, EpisodeSummary, Scene, VecEnv, ACT_DIM};
use crate::learn::{Learner, Rollout, UpdateStats};

pub use super::job::PARAM_CHECK_INTERVAL;
pub use super::run_dir::{RunDir, RunLock, LATEST};
pub use super::setup::keep_runner_settings;

/// Called once per iteration with the row just logged (for the rerun logger, tests).
pub trait IterationObserver {
    fn on_iteration(&mut self, _row: &IterationRow, _learner: &Learner) -> Result<()> {
        Ok(())
    }
    /// Whether an RMA run stops when its phase 1 ends, before phase 2 starts (the
    /// experiment chooses the teacher there; `rall train --stop-after-phase-one`).
    fn stop_after_phase_one(&self) -> bool {
        false
    }
}

impl IterationObserver for () {}

/// Wraps an observer so that training stops at the end of RMA's phase 1.
pub struct PhaseOneOnly<'a>(pub &'a mut dyn IterationObserver);

impl IterationObserver for PhaseOneOnly<'_> {
    fn on_iteration(&mut self, row: &IterationRow, learner: &Learner) -> Result<()> {
        self.0.on_iteration(row, learner)
    }
    fn stop_after_phase_one(&self) -> bool {
        true
    }
}

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
/// (then `cfg` only supplies a new iteration target). One process.
pub fn train(
    cfg: TrainConfig,
    run_dir: &Path,
    resume: bool,
    stop: Arc<AtomicBool>,
    observer: &mut dyn IterationObserver,
) -> Result<TrainSummary> {
    train_in(&World::Single, cfg, run_dir, resume, stop, observer)
}

/// [`train`] as one rank of `world`. Every rank calls it with the same
/// arguments; rank 0's config, checkpoint and parameters are broadcast, and
/// only rank 0 touches `run_dir` (other ranks' `observer` is never called).
pub fn train_in(
    world: &World,
    cfg: TrainConfig,
    run_dir: &Path,
    resume: bool,
    stop: Arc<AtomicBool>,
    observer: &mut dyn IterationObserver,
) -> Result<TrainSummary> {
    Trainer::new(world, cfg, run_dir, resume, stop)?.learn(observer)
}

/// One rank's training run: the learner, its envs and rollout, and the files
/// and counters around them.
pub struct Trainer<'w> {
    world: &'w World,
    dir: RunDir,
    cfg: TrainConfig,
    learner: Learner,
    progress: Progress,
    scene: Scene,
    threads: usize,
    envs: VecEnv,
    /// The envs' current observations.
    obs: Vec<f32>,
    env_seed: u64,
    /// Action noise: each rank its own stream; an exact resume continues it.
    rng: ChaCha8Rng,
    rollout: Rollout,
    /// Episodes finished in this iteration.
    episodes: Vec<EpisodeSummary>,
    /// Statistics of the last iteration in which episodes finished.
    last_stats: EpisodeStats,
    /// `metrics.csv` (rank 0).
    metrics: Option<MetricsCsv>,
    bar: ProgressBar,
    faults: FaultHooks,
    stop: Arc<AtomicBool>,
    wall_start: Instant,
    instabilities_before: u64,
    last_checkpoint: PathBuf,
    /// What a divergence names as the last good state (none before the first save).
    last_good: Option<PathBuf>,
    /// One trainer per run directory (rank 0).
    _lock: Option<RunLock>,
}

/// What one iteration's collection measured on this rank.
struct Collected {
    collect_s: f64,
    times: CollectTimes,
    risk_exceeded: [u64; NUM_RISK_TERMS],
    risk_fired: [u64; NUM_RISK_TERMS],
}

impl<'w> Trainer<'w> {
    /// Takes the run directory (rank 0), starts or resumes the run, and builds
    /// this rank's envs.
    pub fn new(
        world: &'w World,
        cfg: TrainConfig,
        run_dir: &Path,
        resume: bool,
        stop: Arc<AtomicBool>,
    ) -> Result<Trainer<'w>> {
        let dir = RunDir {
            root: run_dir.to_path_buf(),
        };
        let lock = take_run_dir(world, &dir)?;
        let Opened {
            cfg,
            learner,
            progress,
            resumed_from,
            exact,
        } = open_run(world, &dir, cfg, resume)?;
        let threads = size_thread_pools(world, cfg.runner.threads);
        cfg.runner.check_memory(cfg.env.obs_width())?;
        let scene = build_scene(&cfg.env, cfg.runner.seed).context("building the scene")?;
        let start = start_envs(
            &cfg,
            &scene,
            threads,
            world.rank(),
            &progress,
            exact.as_deref(),
        )?;
        let rng = start.action_rng.unwrap_or_else(|| {
            let mut r = ChaCha8Rng::seed_from_u64(rank_seed(progress.rng_seed, world.rank()));
            r.set_word_pos(progress.rng_word_pos);
            r
        });
        let r = &cfg.runner;
        let rollout = Rollout::new(r.steps_per_env, r.num_envs, start.envs.obs_width(), ACT_DIM);
        // a resumed run continues from its checkpoint: later rows are dropped
        let metrics = match world.is_root() {
            true => Some(MetricsCsv::open_resumed(
                &dir.metrics(),
                progress.iteration,
            )?),
            false => None,
        };
        let bar = match world.is_root() {
            true => progress_bar(progress.iteration, r.iterations),
            false => ProgressBar::hidden(),
        };
        Ok(Trainer {
            world,
            last_checkpoint: dir.latest(),
            dir,
            episodes: Vec::with_capacity(r.num_envs * 4),
            wall_start: Instant::now() - std::time::Duration::from_secs_f64(progress.wall_s),
            instabilities_before: start.envs.instabilities(),
            faults: FaultHooks::from_env()?,
            cfg,
            learner,
            progress,
            scene,
            threads,
            envs: start.envs,
            obs: start.obs,
            env_seed: start.env_seed,
            rng,
            rollout,
            last_stats: start.last_stats,
            metrics,
            bar,
            stop,
            last_good: resumed_from,
            _lock: lock,
        })
    }

    /// PPO's outer loop: collect a rollout, update, log, checkpoint; then RMA's
    /// phase 2 (if any), or a last checkpoint when stopped.
    pub fn learn(mut self, observer: &mut dyn IterationObserver) -> Result<TrainSummary> {
        while self.progress.iteration < self.cfg.runner.iterations {
            // a signal on any rank stops all of them at the same iteration
            if any_rank_stopped(self.world, &self.stop) {
                return self.finish_interrupted();
            }
            self.apply_action_std_reset();
            let collected = self.collect()?;
            let (update, learn_s) = self.update()?;
            let job = self.reduce_over_ranks(&collected);
            let env_steps = self.advance(&job);
            self.log(&collected, (&update, learn_s), &job, env_steps, observer)?;
            self.checkpoint_if_due()?;
        }
        self.finish(observer)
    }

    /// Rank 0 speaks for the job.
    fn say(&self, line: String) {
        if self.world.is_root() {
            log_line(&self.bar, line)
        }
    }

    /// `runner.action_std_reset`: the action std set anew after its iteration.
    fn apply_action_std_reset(&mut self) {
        let Some(reset) = self.cfg.runner.action_std_reset else {
            return;
        };
        if self.progress.iteration == reset.after_iteration {
            self.learner.reset_action_std(reset.action_std);
            self.say(format!(
                "iteration {}: action std set to {} for the rest of the run (runner.action_std_reset)",
                self.progress.iteration + 1,
                reset.action_std
            ));
        }
    }

    /// Steps every env `steps_per_env` times with the policy's sampled actions
    /// into the rollout; finished episodes go to `self.episodes`.
    fn collect(&mut self) -> Result<Collected> {
        let t0 = Instant::now();
        self.episodes.clear();
        self.rollout.clear();
        let mut risk_exceeded = [0u64; NUM_RISK_TERMS];
        let mut risk_fired = [0u64; NUM_RISK_TERMS];
        let mut inference_s = 0.0;
        for _ in 0..self.cfg.runner.steps_per_env {
            let ti = Instant::now();
            let out = self.learner.act(&self.obs, &mut self.rng);
            inference_s += ti.elapsed().as_secs_f64();
            let b = self.envs.step(&out.actions);
            for k in 0..NUM_RISK_TERMS {
                risk_exceeded[k] += b.risk_exceeded[k];
                risk_fired[k] += b.risk_fired[k];
            }
            let (rewards, dones, time_outs) = (&b.rewards, &b.dones, &b.time_outs);
            self.rollout
                .push(&self.obs, &out, rewards, dones, time_outs, &b.final_obs)?;
            self.obs.copy_from_slice(&b.obs);
            self.episodes.extend(self.envs.drain_episodes());
        }
        self.rollout.set_last_obs(&self.obs)?;
        let collect_s = t0.elapsed().as_secs_f64();
        Ok(Collected {
            collect_s,
            times: collect_times(&mut self.envs, collect_s, inference_s),
            risk_exceeded,
            risk_fired,
        })
    }

    /// One PPO update on the rollout (gradients averaged over the ranks), with
    /// the fault hooks and the divergence stop. Returns its statistics and seconds.
    fn update(&mut self) -> Result<(UpdateStats, f64)> {
        let t1 = Instant::now();
        let update = self.learner.update_with(&self.rollout, self.world)?;
        let learn_s = t1.elapsed().as_secs_f64();
        self.faults.after_update(
            &mut self.learner,
            &update,
            self.world.rank(),
            self.progress.iteration + 1,
            self.last_good.as_deref(),
        )?;
        Ok((update, learn_s))
    }

    /// This iteration's statistics summed over every rank; warns of physics failures.
    fn reduce_over_ranks(&mut self, c: &Collected) -> JobIteration {
        let local_new = self.envs.instabilities() - self.instabilities_before;
        self.instabilities_before += local_new;
        let c_dt = &self.cfg.env.control;
        let lin_weight_dt = self.cfg.env.reward.lin_vel_tracking * c_dt.policy_dt_s();
        let job = JobIteration::reduce(
            self.world,
            EpisodeStats::from_episodes(&self.episodes, lin_weight_dt),
            &c.risk_exceeded,
            &c.risk_fired,
            self.envs.mean_terrain_level(),
            [local_new, self.envs.instabilities()],
        );
        let new_instabilities = job.instabilities[0];
        if new_instabilities > 0 {
            self.say(format!(
                "warning: iteration {}: {new_instabilities} physics failures (MuJoCo flagged a bad state; those episodes were reset). Many mean the physics dt or the gains are off.",
                self.progress.iteration + 1
            ));
        }
        job
    }

    /// Counts the iteration done; returns the env steps it collected over all ranks.
    fn advance(&mut self, job: &JobIteration) -> u64 {
        let r = &self.cfg.runner;
        let iteration_env_steps = (r.num_envs * r.steps_per_env * self.world.size()) as u64;
        let p = &mut self.progress;
        p.iteration += 1;
        p.total_env_steps += iteration_env_steps;
        p.wall_s = self.wall_start.elapsed().as_secs_f64();
        p.rng_word_pos = self.rng.get_word_pos();
        if job.episodes.episodes > 0 {
            self.last_stats = job.episodes.clone();
        }
        iteration_env_steps
    }

    /// Appends the iteration's row to `metrics.csv` (rank 0, then the observer)
    /// and shows the status line: in the log every `log_interval` iterations.
    fn log(
        &mut self,
        collected: &Collected,
        (update, learn_s): (&UpdateStats, f64),
        job: &JobIteration,
        iteration_env_steps: u64,
        observer: &mut dyn IterationObserver,
    ) -> Result<()> {
        let row = IterationRow {
            iteration: self.progress.iteration,
            wall_s: self.progress.wall_s,
            total_env_steps: self.progress.total_env_steps,
            iteration_env_steps,
            collect_s: collected.collect_s,
            learn_s,
            collect_times: collected.times,
            episodes: &self.last_stats,
            update,
            terrain_level: job.terrain_level,
            risk_exceeded: &job.risk_exceeded,
            risk_fired: &job.risk_fired,
            risk_fired_before_fall: &job.episodes.risk_fired_before_fall,
            instabilities: job.instabilities[1],
            ranks: self.world.size(),
        };
        if let Some(m) = self.metrics.as_mut() {
            m.write(&row)?;
            observer.on_iteration(&row, &self.learner)?;
        }
        self.bar.set_position(row.iteration as u64);
        let status = status_line(&row);
        if row.iteration.is_multiple_of(self.cfg.runner.log_interval) || row.iteration == 1 {
            self.say(status.clone());
            self.say(time_split(&row.collect_times, &update.time));
        }
        self.bar.set_message(status);
        Ok(())
    }

    /// Every `save_interval` iterations and at the end: the checkpoints, after
    /// checking that the ranks agree (also every [`PARAM_CHECK_INTERVAL`]).
    fn checkpoint_if_due(&mut self) -> Result<()> {
        let (r, it) = (&self.cfg.runner, self.progress.iteration);
        let save = it.is_multiple_of(r.save_interval) || it == r.iterations;
        if self.world.size() > 1 && (save || it.is_multiple_of(PARAM_CHECK_INTERVAL)) {
            check_same_state(self.world, &self.learner, it)?;
        }
        if save {
            self.save_checkpoint()?;
            self.last_good = Some(self.last_checkpoint.clone());
        }
        Ok(())
    }

    /// Writes the checkpoints with every rank's state (rank 0 writes).
    fn save_checkpoint(&mut self) -> Result<()> {
        let state = (&self.envs, &self.obs[..], &self.last_stats, &self.rng);
        self.last_checkpoint = save_job_checkpoint(
            self.world,
            &self.dir,
            &self.learner,
            &self.cfg,
            &mut self.progress,
            state,
        )?;
        Ok(())
    }

    /// After the PPO iterations: RMA's phase 2 when the run has one (in one
    /// process, unless the observer stops at phase 1's end).
    fn finish(mut self, observer: &dyn IterationObserver) -> Result<TrainSummary> {
        let adaptation = self.cfg.learner.adaptation.is_some();
        let at_phase_one_end = adaptation && self.progress.iteration == self.cfg.runner.iterations;
        if at_phase_one_end && observer.stop_after_phase_one() {
            self.say(format!(
                "RMA phase 1 done at iteration {}; stopping before phase 2 (resume to run it)",
                self.progress.iteration
            ));
        } else if self.world.size() > 1 && adaptation {
            self.say(format!(
                "RMA phase 1 done at iteration {}; run phase 2 in one process: rall train --resume {}",
                self.progress.iteration,
                self.dir.root.display()
            ));
        } else if self.run_adaptation_phase()? {
            return Ok(self.summary(true));
        }
        Ok(self.summary(false))
    }

    /// RMA's phase 2 (nothing for a run without one); whether it was stopped.
    fn run_adaptation_phase(&mut self) -> Result<bool> {
        let rebuild = EnvRebuildInputs {
            scene: &self.scene,
            threads: self.threads,
            env_seed: self.env_seed,
        };
        let (stopped, written) = adaptation_phase(
            &self.dir,
            &mut self.cfg,
            &mut self.learner,
            &mut self.progress,
            &mut self.envs,
            &mut self.obs,
            &rebuild,
            &self.stop,
            &self.bar,
        )?;
        if let Some(path) = written {
            self.last_checkpoint = path;
        }
        Ok(stopped)
    }

    /// A stopped run: the ranks' states compared, a last checkpoint written.
    fn finish_interrupted(mut self) -> Result<TrainSummary> {
        if self.world.size() > 1 {
            check_same_state(self.world, &self.learner, self.progress.iteration)?;
        }
        self.save_checkpoint()?;
        self.say(format!(
            "interrupted: checkpoint written at iteration {}",
            self.progress.iteration
        ));
        Ok(self.summary(true))
    }

    fn summary(self, interrupted: bool) -> TrainSummary {
        self.bar.finish_and_clear();
        TrainSummary {
            run_dir: self.dir.root.clone(),
            iterations_done: self.progress.iteration,
            interrupted,
            last_checkpoint: self.last_checkpoint,
            final_episode_stats: self.last_stats,
        }
    }
}

/// Rank 0 creates the run directory, takes its lock and removes the temp files
/// a killed write left (another trainer's are not ours to remove).
fn take_run_dir(world: &World, dir: &RunDir) -> Result<Option<RunLock>> {
    if !world.is_root() {
        return Ok(None);
    }
    std::fs::create_dir_all(&dir.root)
        .with_context(|| format!("creating run directory {}", dir.root.display()))?;
    let lock = RunLock::acquire(&dir.root)?;
    dir.remove_temp_files();
    Ok(Some(lock))
}

/// The env worker threads; the learner runs on rayon's global pool, given the
/// same number (settable once per process; `rall train` sets it here first).
fn size_thread_pools(world: &World, threads_setting: usize) -> usize {
    let threads = crate::config::worker_threads(threads_setting);
    let _ = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global();
    if rayon::current_num_threads() != threads && world.is_root() {
        eprintln!(
            "note: the learner uses {} threads (this process's rayon pool was sized before this run), the envs {threads}",
            rayon::current_num_threads()
        );
    }
    threads
}

/// Where the collection's time went: the envs' own split, the policy's
/// inference, and the rest (the rollout's storage).
fn collect_times(envs: &mut VecEnv, collect_s: f64, inference_s: f64) -> CollectTimes {
    let step_times = envs.take_times();
    CollectTimes {
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
    }
}
