//! The training loop: collect `steps_per_env` steps from every env, update,
//! log, checkpoint. Resumable; Ctrl-C writes a last checkpoint.
//!
//! Data-parallel under MPI ([`World`]): every rank runs this loop over its own
//! `num_envs` environments (own seeds, own terrain curriculum) and the update
//! averages the gradients of all ranks, so all hold the same parameters; rank 0
//! alone writes the run directory. Ranks compare a hash of their learner state
//! every [`PARAM_CHECK_INTERVAL`] iterations and at every checkpoint.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use super::dist::{diverged_ranks, hash_f32, rank_seed, World};
use super::metrics::{CollectTimes, EpisodeStats, IterationRow, MetricsCsv};
use super::policy_file::{load_policy, load_policy_bytes, save_policy, Progress};
use super::resume::{exact_state, gather_rank_states, start_envs};
use crate::config::TrainConfig;
use crate::env::risk::NUM_RISK_TERMS;
use crate::env::{build_scene, EpisodeSummary, VecEnv, ACT_DIM};
use crate::learn::{Collective, Learner, Rollout, UpdateStats, UpdateTimes};

/// Iterations between two comparisons of the ranks' learner state (MPI).
pub const PARAM_CHECK_INTERVAL: usize = 10;

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

    /// Removes the temp files a killed or failed write of rall left behind
    /// (only its own names: a shared folder's other `*.tmp` files stay).
    fn remove_temp_files(&self) {
        for (d, in_checkpoints) in [
            (self.root.clone(), false),
            (self.root.join("checkpoints"), true),
        ] {
            let Ok(entries) = std::fs::read_dir(&d) else {
                continue;
            };
            for e in entries.flatten() {
                let name = e.file_name();
                let ours = name
                    .to_str()
                    .is_some_and(|n| crate::fsio::is_rall_temp(n, in_checkpoints));
                if ours && e.file_type().is_ok_and(|t| t.is_file()) {
                    let _ = std::fs::remove_file(e.path());
                }
            }
        }
    }

    /// Numbered checkpoints, newest first.
    fn numbered_checkpoints(&self) -> Vec<PathBuf> {
        let mut found = self.checkpoints_by_iteration();
        found.reverse();
        found.into_iter().map(|(_, p)| p).collect()
    }

    /// `checkpoints/model_<iteration>.safetensors`, oldest first, with their iterations.
    pub fn checkpoints_by_iteration(&self) -> Vec<(usize, PathBuf)> {
        let mut found: Vec<(usize, PathBuf)> = std::fs::read_dir(self.root.join("checkpoints"))
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|e| {
                let name = e.file_name().into_string().ok()?;
                let it = name
                    .strip_prefix("model_")?
                    .strip_suffix(".safetensors")?
                    .parse()
                    .ok()?;
                Some((it, e.path()))
            })
            .collect();
        found.sort_by_key(|f| f.0);
        found
    }

    /// The config of a run stopped before it wrote any checkpoint (nothing to
    /// resume, but the run can start again), or `None` when it has a checkpoint
    /// file or no `config.toml`.
    pub fn config_before_first_checkpoint(&self) -> Result<Option<TrainConfig>> {
        let stored = self.root.join("config.toml");
        if self.latest().exists() || !self.numbered_checkpoints().is_empty() || !stored.exists() {
            return Ok(None);
        }
        TrainConfig::from_toml_file(&stored).map(Some)
    }

    /// The checkpoint to resume from: `latest`, or when it is missing,
    /// unreadable or corrupt the newest numbered checkpoint that loads intact.
    /// Says nothing (see [`RunDir::resume_point_noting`]).
    pub fn resume_point(&self) -> Result<(PathBuf, crate::runner::LoadedPolicy)> {
        self.find_resume_point().map(|f| (f.path, f.loaded))
    }

    fn find_resume_point(&self) -> Result<Found> {
        let latest = self.latest();
        let resumable = |path: &Path| {
            load_policy(path).and_then(|loaded| {
                if loaded.actor_only {
                    anyhow::bail!(
                        "{} holds the actor alone (an evaluation copy): it cannot be resumed",
                        path.display()
                    )
                }
                Ok(loaded)
            })
        };
        let latest_err = match resumable(&latest) {
            Ok(loaded) => {
                return Ok(Found {
                    path: latest,
                    loaded,
                    passed_over: Vec::new(),
                })
            }
            Err(e) => e,
        };
        let mut passed_over = vec![(latest, format!("{latest_err:#}"))];
        for path in self.numbered_checkpoints() {
            match resumable(&path) {
                Ok(loaded) => {
                    return Ok(Found {
                        path,
                        loaded,
                        passed_over,
                    })
                }
                Err(e) => passed_over.push((path, format!("{e:#}"))),
            }
        }
        Err(latest_err).with_context(|| {
            format!(
                "cannot resume {}: no readable checkpoint (latest or checkpoints/model_*)",
                self.root.display()
            )
        })
    }

    /// [`RunDir::resume_point`] for the run about to resume: says once which
    /// checkpoint it falls back to and why, and moves the unreadable numbered
    /// checkpoints it passed over aside (`<name>.corrupt`), so that nothing
    /// picks them up later.
    fn resume_point_noting(&self) -> Result<(PathBuf, crate::runner::LoadedPolicy)> {
        let found = self.find_resume_point()?;
        if let Some((first, why)) = found.passed_over.first() {
            let mut note = format!(
                "note: {} is unusable ({why}); resuming from {}",
                first.display(),
                found.path.display()
            );
            for (p, _) in &found.passed_over[1..] {
                let mut aside = p.as_os_str().to_owned();
                aside.push(".corrupt");
                if std::fs::rename(p, &aside).is_ok() {
                    note.push_str(&format!(
                        "; unreadable {} moved to {}",
                        p.display(),
                        Path::new(&aside).display()
                    ));
                }
            }
            eprintln!("{note}");
        }
        Ok((found.path, found.loaded))
    }
}

/// A resume point and the unusable checkpoints passed over on the way (path, why).
struct Found {
    path: PathBuf,
    loaded: crate::runner::LoadedPolicy,
    passed_over: Vec<(PathBuf, String)>,
}

/// Held while a process trains in a run directory: `train.lock` with its pid.
/// A lock whose process is gone (killed) is taken over.
pub struct RunLock {
    path: PathBuf,
}

impl RunLock {
    pub fn acquire(root: &Path) -> Result<RunLock> {
        use std::io::Write as _;
        let path = root.join("train.lock");
        for _ in 0..3 {
            match std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&path)
            {
                Ok(mut f) => {
                    writeln!(f, "{}", std::process::id())
                        .with_context(|| format!("writing {}", path.display()))?;
                    return Ok(RunLock { path });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let holder = std::fs::read_to_string(&path)
                        .ok()
                        .and_then(|t| t.trim().parse::<u32>().ok());
                    if let Some(pid) = holder.filter(|pid| process_alive(*pid)) {
                        anyhow::bail!(
                            "{} is being trained by process {pid} ({} holds its pid): wait for it or stop it; remove the file only if that process is not rall",
                            root.display(),
                            path.display()
                        );
                    }
                    // left by a process that died (kill -9): take it over
                    let _ = std::fs::remove_file(&path);
                }
                Err(e) => {
                    return Err(e).with_context(|| format!("creating {}", path.display()));
                }
            }
        }
        anyhow::bail!("could not take {}", path.display())
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Whether process `pid` exists and has not exited (Linux /proc; a zombie,
/// e.g. an MPI rank whose launcher is gone and not yet reaped, is dead).
fn process_alive(pid: u32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        // "pid (comm) S ...": the state follows the last ')'
        Ok(stat) => stat
            .rsplit_once(')')
            .and_then(|(_, rest)| rest.split_whitespace().next())
            .is_some_and(|state| state != "Z" && state != "X"),
        Err(_) => false,
    }
}

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
    let dir = RunDir {
        root: run_dir.to_path_buf(),
    };
    let (rank, ranks, root) = (world.rank(), world.size(), world.is_root());
    // one trainer per run directory (another one's temp files are not ours to remove)
    let _lock = if root {
        std::fs::create_dir_all(&dir.root)
            .with_context(|| format!("creating run directory {}", dir.root.display()))?;
        let lock = RunLock::acquire(&dir.root)?;
        dir.remove_temp_files();
        Some(lock)
    } else {
        None
    };
    let mut cfg = cfg;
    // rank 0 picks and loads the checkpoint (none: the run starts again)
    let (mut path, mut resumed) = (PathBuf::new(), None);
    if resume && root {
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
    if resume && ranks > 1 {
        // the other ranks load the same file's bytes (empty: no checkpoint)
        let mut bytes = match &resumed {
            Some(_) => std::fs::read(&path)
                .with_context(|| format!("reading checkpoint {}", path.display()))?,
            None => Vec::new(),
        };
        world.broadcast_bytes(&mut bytes);
        if !root && !bytes.is_empty() {
            path = PathBuf::from("<rank 0's checkpoint>");
            resumed = Some(load_policy_bytes(&bytes, &path)?);
        }
    }
    let resume = resumed.is_some();
    let exact = match &resumed {
        Some(loaded) => match exact_state(&loaded.progress, loaded.exact, rank, ranks) {
            Ok(state) => Some(state),
            Err(why) => {
                if root {
                    eprintln!(
                        "note: {} resumes, but not bit-identically to an uninterrupted run: {why}",
                        path.display()
                    );
                }
                None
            }
        },
        None => None,
    };
    if let Some(loaded) = resumed.as_ref().filter(|_| root && exact.is_some()) {
        let (then, now) = (loaded.config.runner.threads, cfg.runner.threads);
        if then != now {
            eprintln!(
                "note: {} was trained with runner.threads = {then}, this resume uses {now}: the update sums its shards in another order, so the run is not bit-identical to an uninterrupted one",
                path.display()
            );
        }
    }
    let (mut cfg, mut learner, mut progress) = if let Some(loaded) = resumed {
        let stored = keep_runner_settings(loaded.config, &cfg, loaded.progress.iteration)
            .with_context(|| format!("resuming from {}", path.display()))?;
        if root {
            println!(
                "resuming {} from {} at iteration {} (lr {:.2e}); {} envs x {} steps{}, {}, seed {}",
                dir.root.display(),
                path.display(),
                loaded.progress.iteration,
                loaded.learner.learning_rate(),
                stored.runner.num_envs,
                stored.runner.steps_per_env,
                ranks_note(ranks),
                stored.learner.risk_label(),
                stored.runner.seed
            );
        }
        (stored, loaded.learner, loaded.progress)
    } else {
        cfg.validate()?;
        if root {
            println!(
                "training {} envs x {} steps{}, critic {:?}, {}, seed {} -> {}",
                cfg.runner.num_envs,
                cfg.runner.steps_per_env,
                ranks_note(ranks),
                cfg.learner.critic,
                cfg.learner.risk_label(),
                cfg.runner.seed,
                dir.root.display()
            );
        }
        let (learner, progress) = fresh_start(&cfg)?;
        (cfg, learner, progress)
    };
    if root && cfg.learner.ppo.matmul != crate::learn::mat::Precision::F32 {
        println!(
            "update matmuls in bf16 (f32 sums): {}",
            crate::learn::mat::precision_backend(cfg.learner.ppo.matmul)
        );
    }
    if ranks > 1 {
        // rank 0's settings and parameters on every rank (runner overrides included)
        let mut toml = cfg.to_toml().into_bytes();
        world.broadcast_bytes(&mut toml);
        cfg = TrainConfig::from_toml_str(&String::from_utf8_lossy(&toml))
            .context("the config broadcast by rank 0")?;
        if !resume && !root {
            // networks of rank 0's config (a restarted run's stored one)
            (learner, progress) = fresh_start(&cfg)?;
        }
        broadcast_learner_state(world, &mut learner)?;
        if cfg.learner.adaptation.is_some() && root {
            println!("note: RMA phase 2 (the adaptation module) runs in one process: after phase 1, resume the run without mpirun");
        }
    }
    if root {
        crate::fsio::write_atomic(&dir.root.join("config.toml"), cfg.to_toml().as_bytes())?;
    }

    let r = &cfg.runner;
    let threads = crate::config::worker_threads(r.threads);
    // the learner runs on rayon's global pool: give it the same threads as the
    // envs' pool (settable once per process; `rall train` sets it here first)
    let _ = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global();
    if rayon::current_num_threads() != threads && root {
        eprintln!(
            "note: the learner uses {} threads (this process's rayon pool was sized before this run), the envs {threads}",
            rayon::current_num_threads()
        );
    }
    r.check_memory(cfg.env.obs_width())?;
    let scene = build_scene(&cfg.env, r.seed).context("building the scene")?;
    let exact = exact.as_deref();
    let start = start_envs(&cfg, &scene, threads, rank, &progress, exact)?;
    let (mut envs, mut obs, mut last_stats, env_seed) =
        (start.envs, start.obs, start.last_stats, start.env_seed);
    // action noise: each rank its own stream; an exact resume continues it
    let mut rng = start.action_rng.unwrap_or_else(|| {
        let mut r = ChaCha8Rng::seed_from_u64(rank_seed(progress.rng_seed, rank));
        r.set_word_pos(progress.rng_word_pos);
        r
    });
    let mut rollout = Rollout::new(r.steps_per_env, r.num_envs, envs.obs_width(), ACT_DIM);
    // a resumed run continues from its checkpoint: later rows are dropped
    let mut metrics = match root {
        true => Some(MetricsCsv::open_resumed(
            &dir.metrics(),
            progress.iteration,
        )?),
        false => None,
    };
    let lin_weight_dt = cfg.env.reward.lin_vel_tracking * cfg.env.control.policy_dt_s();

    let bar = match root {
        true => progress_bar(progress.iteration, r.iterations),
        false => ProgressBar::hidden(),
    };
    // rank 0 speaks for the job
    let say = |line: String| {
        if root {
            log_line(&bar, line)
        }
    };
    let mut episodes: Vec<EpisodeSummary> = Vec::with_capacity(r.num_envs * 4);
    let mut interrupted = false;
    let mut last_checkpoint = dir.latest();
    // what a divergence names as the last good state (none before the first save)
    let mut last_good: Option<PathBuf> = resume.then(|| path.clone());
    let wall_start = Instant::now() - std::time::Duration::from_secs_f64(progress.wall_s);
    let mut instabilities_before = envs.instabilities();
    let fault = divergence_fault()?;
    let nan_fault = nan_fault()?;

    while progress.iteration < r.iterations {
        // a signal on any rank stops all of them at the same iteration
        let mut stop_votes = [stop.load(Ordering::SeqCst) as u8 as f64];
        world.sum_f64(&mut stop_votes);
        if stop_votes[0] > 0.0 {
            interrupted = true;
            break;
        }
        if let Some(reset) = r.action_std_reset {
            if progress.iteration == reset.after_iteration {
                learner.reset_action_std(reset.action_std);
                if root {
                    log_line(
                        &bar,
                        format!(
                            "iteration {}: action std set to {} for the rest of the run (runner.action_std_reset)",
                            progress.iteration + 1,
                            reset.action_std
                        ),
                    );
                }
            }
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
        let update: UpdateStats = learner.update_with(&rollout, world)?;
        let learn_s = t1.elapsed().as_secs_f64();
        if nan_fault == Some(progress.iteration + 1) {
            poison_one_weight(&mut learner)?;
        }
        ensure_finite(
            &update,
            &learner,
            progress.iteration + 1,
            last_good.as_deref(),
        )?;
        if fault == Some((rank, progress.iteration + 1)) {
            nudge_one_weight(&mut learner)?;
        }
        // this iteration's statistics over all ranks
        let local_new = envs.instabilities() - instabilities_before;
        instabilities_before += local_new;
        let job = JobIteration::reduce(
            world,
            EpisodeStats::from_episodes(&episodes, lin_weight_dt),
            &risk_exceeded,
            &risk_fired,
            envs.mean_terrain_level(),
            [local_new, envs.instabilities()],
        );
        let (risk_exceeded, risk_fired) = (job.risk_exceeded, job.risk_fired);
        let [new_instabilities, all_instabilities] = job.instabilities;
        if new_instabilities > 0 {
            say(format!(
                "warning: iteration {}: {new_instabilities} physics failures (MuJoCo flagged a bad state; those episodes were reset). Many mean the physics dt or the gains are off.",
                progress.iteration + 1
            ));
        }

        progress.iteration += 1;
        let iteration_env_steps = (r.num_envs * r.steps_per_env * ranks) as u64;
        progress.total_env_steps += iteration_env_steps;
        progress.wall_s = wall_start.elapsed().as_secs_f64();
        progress.rng_word_pos = rng.get_word_pos();
        let fired_before_fall = job.episodes.risk_fired_before_fall;
        if job.episodes.episodes > 0 {
            last_stats = job.episodes;
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
            terrain_level: job.terrain_level,
            risk_exceeded: &risk_exceeded,
            risk_fired: &risk_fired,
            risk_fired_before_fall: &fired_before_fall,
            instabilities: all_instabilities,
            ranks,
        };
        if let Some(m) = metrics.as_mut() {
            m.write(&row)?;
            observer.on_iteration(&row, &learner)?;
        }
        bar.set_position(progress.iteration as u64);
        let status = format!(
            "it {:>5} | {:>7.1} min | {:>6.0} steps/s | collect {:.2}s learn {:.2}s | return {:>7.3} | len {:>5.0} | track {:.3} | falls {:>3}/{:<3} | level {:.2} | risk {}/{} | lr {:.1e} (mean {:.1e}) | std {:.3} | value loss {:.4}",
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
            update.learning_rate_mean,
            update.mean_std,
            update.value_loss,
        );
        if progress.iteration.is_multiple_of(r.log_interval) || progress.iteration == 1 {
            say(status.clone());
            say(time_split(&collect_times, &update.time));
        }
        bar.set_message(status);
        episodes.clear();
        let save = progress.iteration.is_multiple_of(r.save_interval)
            || progress.iteration == r.iterations;
        if ranks > 1 && (save || progress.iteration.is_multiple_of(PARAM_CHECK_INTERVAL)) {
            check_same_state(world, &learner, progress.iteration)?;
        }
        if save {
            last_checkpoint = save_job_checkpoint(
                world,
                &dir,
                &learner,
                &cfg,
                &mut progress,
                (&envs, &obs, &last_stats, &rng),
            )?;
            last_good = Some(last_checkpoint.clone());
        }
    }
    let at_phase_one_end =
        cfg.learner.adaptation.is_some() && progress.iteration == cfg.runner.iterations;
    if !interrupted && at_phase_one_end && observer.stop_after_phase_one() {
        say(format!(
            "RMA phase 1 done at iteration {}; stopping before phase 2 (resume to run it)",
            progress.iteration
        ));
    } else if !interrupted && ranks > 1 && cfg.learner.adaptation.is_some() {
        say(format!(
            "RMA phase 1 done at iteration {}; run phase 2 in one process: rall train --resume {}",
            progress.iteration,
            dir.root.display()
        ));
    } else if !interrupted {
        let world = super::adapt::PhaseWorld {
            scene: &scene,
            threads,
            env_seed,
        };
        let (stopped, written) = super::adapt::adaptation_phase(
            &dir,
            &mut cfg,
            &mut learner,
            &mut progress,
            &mut envs,
            &mut obs,
            &world,
            &stop,
            &bar,
        )?;
        if let Some(path) = written {
            last_checkpoint = path;
        }
        if stopped {
            bar.finish_and_clear();
            return Ok(TrainSummary {
                run_dir: dir.root.clone(),
                iterations_done: progress.iteration,
                interrupted: true,
                last_checkpoint,
                final_episode_stats: last_stats,
            });
        }
    }
    if interrupted {
        if ranks > 1 {
            check_same_state(world, &learner, progress.iteration)?;
        }
        last_checkpoint = save_job_checkpoint(
            world,
            &dir,
            &learner,
            &cfg,
            &mut progress,
            (&envs, &obs, &last_stats, &rng),
        )?;
        say(format!(
            "interrupted: checkpoint written at iteration {}",
            progress.iteration
        ));
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

/// " on N ranks" for N > 1.
fn ranks_note(ranks: usize) -> String {
    match ranks {
        1 => String::new(),
        n => format!(" on each of {n} ranks"),
    }
}

/// One iteration's statistics summed (means: averaged) over every rank.
struct JobIteration {
    episodes: EpisodeStats,
    risk_exceeded: [u64; NUM_RISK_TERMS],
    risk_fired: [u64; NUM_RISK_TERMS],
    terrain_level: f64,
    instabilities: [u64; 2],
}

impl JobIteration {
    /// One sum across ranks of everything the metrics row reports.
    fn reduce(
        world: &World,
        episodes: EpisodeStats,
        risk_exceeded: &[u64; NUM_RISK_TERMS],
        risk_fired: &[u64; NUM_RISK_TERMS],
        terrain_level: f64,
        instabilities: [u64; 2],
    ) -> JobIteration {
        let mut v = episodes.sums();
        let n_ep = v.len();
        v.extend(risk_exceeded.iter().chain(risk_fired).map(|x| *x as f64));
        v.push(terrain_level);
        v.extend(instabilities.map(|x| x as f64));
        world.sum_f64(&mut v);
        let count = |k: usize| v[k].round() as u64;
        let k = n_ep + 2 * NUM_RISK_TERMS;
        JobIteration {
            episodes: EpisodeStats::from_sums(&v[..n_ep]),
            risk_exceeded: std::array::from_fn(|i| count(n_ep + i)),
            risk_fired: std::array::from_fn(|i| count(n_ep + NUM_RISK_TERMS + i)),
            terrain_level: v[k] / world.size() as f64,
            instabilities: [count(k + 1), count(k + 2)],
        }
    }
}

/// Rank `rank`'s terrain levels from a checkpoint's: its own slice when the
/// checkpoint holds every rank's (`ranks x num_envs`), else the stored levels
/// cycled (a checkpoint of another rank count).
pub(super) fn rank_levels(stored: &[usize], rank: usize, num_envs: usize) -> Vec<usize> {
    if stored.is_empty() {
        return Vec::new();
    }
    (0..num_envs)
        .map(|i| stored[(rank * num_envs + i) % stored.len()])
        .collect()
}

/// Rank 0's learner state (weights, Adam moments, step, lr) on every rank.
fn broadcast_learner_state(world: &World, learner: &mut Learner) -> Result<()> {
    let mut state = learner.state();
    let mut bytes: Vec<u8> = state
        .iter()
        .flat_map(|t| t.data.iter().flat_map(|v| v.to_le_bytes()))
        .collect();
    world.broadcast_bytes(&mut bytes);
    let mut values = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]));
    for t in &mut state {
        for v in &mut t.data {
            *v = values
                .next()
                .context("rank 0's learner state is smaller than this rank's")?;
        }
    }
    learner.load_state(&state)
}

/// Compares the ranks' learner state; a divergence stops every rank, naming
/// the ranks that differ from rank 0.
fn check_same_state(world: &World, learner: &Learner, iteration: usize) -> Result<()> {
    let state = learner.state();
    let hash = hash_f32(state.iter().flat_map(|t| t.data.iter().copied()));
    let hashes = world.all_gather_u64(hash);
    let bad = diverged_ranks(&hashes);
    if bad.is_empty() {
        return Ok(());
    }
    anyhow::bail!(
        "the ranks' parameters diverged at iteration {iteration}: rank(s) {bad:?} differ from rank 0 (state hashes {hashes:016x?}); the run stops (resume it from its last checkpoint)"
    )
}

/// Fault injection for the divergence check's test: `RALL_FAULT_PERTURB=<rank>:<iteration>`
/// asks that rank to nudge one weight after that iteration's update.
fn divergence_fault() -> Result<Option<(usize, usize)>> {
    let Ok(spec) = std::env::var("RALL_FAULT_PERTURB") else {
        return Ok(None);
    };
    let target = spec
        .split_once(':')
        .and_then(|(r, i)| Some((r.parse::<usize>().ok()?, i.parse::<usize>().ok()?)));
    match target {
        Some(t) => Ok(Some(t)),
        None => anyhow::bail!("RALL_FAULT_PERTURB={spec:?}: expected <rank>:<iteration>"),
    }
}

/// Fault injection for the divergence stop's test: `RALL_FAULT_NAN=<iteration>`
/// makes one weight NaN after that iteration's update.
fn nan_fault() -> Result<Option<usize>> {
    match std::env::var("RALL_FAULT_NAN") {
        Err(_) => Ok(None),
        Ok(v) => v
            .parse()
            .map(Some)
            .map_err(|_| anyhow::anyhow!("RALL_FAULT_NAN={v:?}: expected an iteration")),
    }
}

/// Sets the first weight to NaN (the injected numerical failure).
fn poison_one_weight(learner: &mut Learner) -> Result<()> {
    let mut state = learner.state();
    state[0].data[0] = f32::NAN;
    learner.load_state(&state)
}

/// Adds 1e-3 to the first weight (the injected divergence).
fn nudge_one_weight(learner: &mut Learner) -> Result<()> {
    let mut state = learner.state();
    state[0].data[0] += 1e-3;
    learner.load_state(&state)
}

/// Writes the checkpoints (rank 0) with every rank's terrain levels.
fn save_job_checkpoint(
    world: &World,
    dir: &RunDir,
    learner: &Learner,
    cfg: &TrainConfig,
    progress: &mut Progress,
    (envs, obs, last_stats, rng): (&VecEnv, &[f32], &EpisodeStats, &ChaCha8Rng),
) -> Result<PathBuf> {
    progress.rank_states = gather_rank_states(world, envs, obs, last_stats, rng)?;
    progress.terrain_levels = match envs.terrain_levels() {
        Some(mine) if world.size() > 1 => {
            // each rank fills its own slice; the sum gathers them all
            let n = mine.len();
            let mut all = vec![0.0f64; n * world.size()];
            let own = &mut all[world.rank() * n..(world.rank() + 1) * n];
            own.iter_mut().zip(&mine).for_each(|(a, l)| *a = *l as f64);
            world.sum_f64(&mut all);
            Some(all.iter().map(|l| l.round() as usize).collect())
        }
        mine => mine,
    };
    if world.is_root() {
        save_both(dir, learner, cfg, progress)
    } else {
        Ok(dir.checkpoint(progress.iteration))
    }
}

/// Stops a run whose update produced a non-finite loss or weights, instead of
/// training (and checkpointing) garbage to the end.
fn ensure_finite(
    u: &UpdateStats,
    learner: &Learner,
    iteration: usize,
    last_good: Option<&Path>,
) -> Result<()> {
    let losses_ok =
        u.policy_loss.is_finite() && u.value_loss.is_finite() && u.grad_norm.is_finite();
    let weights_ok = learner
        .state()
        .iter()
        .all(|t| t.data.iter().all(|v| v.is_finite()));
    if losses_ok && weights_ok {
        return Ok(());
    }
    anyhow::bail!(
        "training diverged at iteration {iteration}: policy loss {}, value loss {}, gradient norm {}{} (check observation scales, reward weights and the physics dt); {}",
        u.policy_loss,
        u.value_loss,
        u.grad_norm,
        if weights_ok { "" } else { ", non-finite weights" },
        match last_good {
            Some(p) => format!("nothing was saved after the last good checkpoint {}", p.display()),
            None => "no checkpoint was written before it".into(),
        }
    )
}

/// Writes the numbered checkpoint and the rolling `latest` one.
pub(super) fn save_both(
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
        "      time | collect: physics {:.3}s task {:.3}s reset {:.3}s inference {:.3}s storage {:.3}s | learn: targets {:.3}s gather {:.3}s forward {:.3}s loss {:.3}s backward {:.3}s clip {:.3}s adam {:.3}s comm {:.3}s",
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
        l.adam_s,
        l.comm_s
    )
}

/// Prints above the bar on a terminal, plainly otherwise (logs of background runs).
pub(super) fn log_line(bar: &ProgressBar, line: String) {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_trainer_per_run_directory_and_dead_holders_are_taken_over() {
        let dir = tempfile::tempdir().unwrap();
        let lock = RunLock::acquire(dir.path()).unwrap();
        let e = format!("{:#}", RunLock::acquire(dir.path()).err().unwrap());
        assert!(e.contains(&std::process::id().to_string()), "{e}");
        drop(lock);
        assert!(!dir.path().join("train.lock").exists());
        // a pid above any pid_max: its holder is gone
        std::fs::write(dir.path().join("train.lock"), "4294967295\n").unwrap();
        let _again = RunLock::acquire(dir.path()).unwrap();
    }

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
