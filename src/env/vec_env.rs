//! [`VecEnv`]: N environments stepped in parallel with rayon, auto-reset,
//! batched buffers allocated once. Each env owns its RNG, so a seed gives
//! bit-identical rollouts whatever the thread count.

use std::sync::Arc;
use std::time::Instant;

use rayon::prelude::*;

use super::config::EnvConfig;
use super::observation::ACT_DIM;
use super::risk::NUM_RISK_TERMS;
use super::single::{Env, EpisodeSummary, StepResult};
use super::snapshot::{StateReader, StateWriter};
use super::terrain::{Curriculum, Terrain};
use crate::sim::{ArenaUse, Model, Result, SimError};

/// Batched outputs of one step, row-major (env-major).
#[derive(Debug, Clone)]
pub struct Batch {
    /// [n x obs_width] observations after the step (new episode's first after a reset).
    pub obs: Vec<f32>,
    pub rewards: Vec<f32>,
    /// The episode ended this step (termination or time-out).
    pub dones: Vec<bool>,
    /// It ended by time-out (the learner bootstraps from `final_obs`).
    pub time_outs: Vec<bool>,
    /// [n x obs_width]: the true last observation of an episode that ended this
    /// step (valid where `dones` is set; zeros after a physics failure).
    pub final_obs: Vec<f32>,
    /// Risk thresholds exceeded / penalties fired this step, summed over envs.
    pub risk_exceeded: [u64; NUM_RISK_TERMS],
    pub risk_fired: [u64; NUM_RISK_TERMS],
    pub pushes: u64,
}

impl Batch {
    fn new(n: usize, width: usize) -> Batch {
        Batch {
            obs: vec![0.0; n * width],
            rewards: vec![0.0; n],
            dones: vec![false; n],
            time_outs: vec![false; n],
            final_obs: vec![0.0; n * width],
            risk_exceeded: [0; NUM_RISK_TERMS],
            risk_fired: [0; NUM_RISK_TERMS],
            pushes: 0,
        }
    }
}

/// Where the wall time of [`VecEnv::step`] went since the last
/// [`VecEnv::take_times`], in seconds. The parallel pass is split between
/// physics and task by the envs' own CPU-time shares.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepTimes {
    /// PD control and `mj_step` x decimation.
    pub physics_s: f64,
    /// Observation, reward, risk terms, pushes, commands.
    pub task_s: f64,
    /// Counters, curriculum and auto-resets after the parallel pass.
    pub reset_s: f64,
}

/// How the envs of a [`VecEnv`] hold their model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ModelSharing {
    /// One model for all envs (terrain stored once); each worker thread keeps
    /// one working copy and writes each env's randomisation in before its step.
    #[default]
    PerThread,
    /// A full model copy per env (the former layout; the reference in tests).
    PerEnv,
}

/// Tag of [`VecEnv::snapshot`]'s layout.
const VEC_ENV_SNAPSHOT_TAG: &str = "rall-vec-env-1";

pub struct VecEnv {
    envs: Vec<Env>,
    times: StepTimes,
    /// Terrain levels and types (rough terrain only).
    curriculum: Option<Curriculum>,
    pool: rayon::ThreadPool,
    batch: Batch,
    /// Episodes finished since the last [`VecEnv::drain_episodes`].
    episodes: Vec<EpisodeSummary>,
    /// Values per observation row.
    obs_width: usize,
}

impl VecEnv {
    /// `n` envs over `base_model` (shared, [`ModelSharing::PerThread`]),
    /// stepped on `threads` threads.
    pub fn new(
        cfg: Arc<EnvConfig>,
        base_model: &Arc<Model>,
        terrain: Option<Arc<Terrain>>,
        n: usize,
        threads: usize,
        seed: u64,
    ) -> Result<VecEnv> {
        VecEnv::with_sharing(
            cfg,
            base_model,
            terrain,
            n,
            threads,
            seed,
            ModelSharing::PerThread,
        )
    }

    /// As [`VecEnv::new`], choosing how the envs hold their model.
    pub fn with_sharing(
        cfg: Arc<EnvConfig>,
        base_model: &Arc<Model>,
        terrain: Option<Arc<Terrain>>,
        n: usize,
        threads: usize,
        seed: u64,
        sharing: ModelSharing,
    ) -> Result<VecEnv> {
        if n == 0 {
            return Err(SimError::Invalid(
                "the number of envs must be at least 1".into(),
            ));
        }
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .thread_name(|i| format!("rall-env-{i}"))
            .build()
            .map_err(|e| SimError::Invalid(format!("cannot start {threads} env threads: {e}")))?;
        let envs = pool.install(|| {
            (0..n)
                .into_par_iter()
                .map(|i| match sharing {
                    ModelSharing::PerThread => {
                        Env::new(cfg.clone(), base_model, terrain.clone(), seed, i)
                    }
                    ModelSharing::PerEnv => {
                        Env::with_own_model(cfg.clone(), base_model, terrain.clone(), seed, i)
                    }
                })
                .collect::<Result<Vec<_>>>()
        })?;
        let curriculum = terrain
            .as_ref()
            .map(|t| Curriculum::new(t.config(), n, seed));
        let mut v = VecEnv {
            envs,
            times: StepTimes::default(),
            curriculum,
            pool,
            batch: Batch::new(n, cfg.obs_width()),
            obs_width: cfg.obs_width(),
            episodes: Vec::with_capacity(4 * n),
        };
        v.sync_terrain_cells();
        v.reset_all()?;
        Ok(v)
    }

    /// Values per observation row (all configured groups).
    pub fn obs_width(&self) -> usize {
        self.obs_width
    }
    pub fn num_envs(&self) -> usize {
        self.envs.len()
    }
    pub fn envs(&self) -> &[Env] {
        &self.envs
    }
    pub fn envs_mut(&mut self) -> &mut [Env] {
        &mut self.envs
    }
    /// The last step's outputs (after [`VecEnv::reset_all`], only `obs` is meaningful).
    pub fn batch(&self) -> &Batch {
        &self.batch
    }

    fn sync_terrain_cells(&mut self) {
        if let Some(c) = &self.curriculum {
            for (i, env) in self.envs.iter_mut().enumerate() {
                env.set_terrain_cell(c.level(i), c.terrain_type(i));
            }
        }
    }

    /// Resets every env and fills `batch().obs`.
    pub fn reset_all(&mut self) -> Result<()> {
        let obs = &mut self.batch.obs;
        let width = self.obs_width;
        self.pool.install(|| {
            self.envs
                .par_iter_mut()
                .zip(obs.par_chunks_mut(width))
                .try_for_each(|(env, o)| env.reset(o))
        })
    }

    /// legged_gym's trick: random episode progress so time-outs spread out.
    pub fn randomize_episode_progress(&mut self) {
        for env in &mut self.envs {
            env.randomize_episode_progress();
        }
    }

    /// Steps all envs with `actions` ([n x ACT_DIM]); results in [`VecEnv::batch`].
    pub fn step(&mut self, actions: &[f32]) -> &Batch {
        self.step_active(actions, None)
    }

    /// Steps the envs whose `active` entry is true (all of them with `None`); the
    /// others stand still: no physics, no RNG draw, their observation unchanged,
    /// reward 0 and not done. Each env steps on its own state and RNG alone, so an
    /// active env's results do not depend on which others stepped.
    pub fn step_active(&mut self, actions: &[f32], active: Option<&[bool]>) -> &Batch {
        assert_eq!(
            actions.len(),
            self.envs.len() * ACT_DIM,
            "actions must be n_envs x {ACT_DIM}"
        );
        if let Some(m) = active {
            assert_eq!(m.len(), self.envs.len(), "one active flag per env");
        }
        let start = Instant::now();
        let width = self.obs_width;
        let b = &mut self.batch;
        self.pool.install(|| {
            self.envs
                .par_iter_mut()
                .zip(actions.par_chunks(ACT_DIM))
                .zip(b.obs.par_chunks_mut(width))
                .zip(b.final_obs.par_chunks_mut(width))
                .zip(b.rewards.par_iter_mut())
                .zip(b.dones.par_iter_mut())
                .zip(b.time_outs.par_iter_mut())
                .enumerate()
                .for_each(|(i, ((((((env, a), o), fo), r), d), t))| {
                    let res = if active.is_none_or(|m| m[i]) {
                        env.step(a, o, fo)
                    } else {
                        StepResult::default()
                    };
                    *r = res.reward as f32;
                    *d = res.done;
                    *t = res.time_out;
                    env.last_step = res;
                });
        });
        let parallel_s = start.elapsed().as_secs_f64();
        let (physics_ns, step_ns) = self.envs.iter_mut().fold((0u64, 0u64), |(p, s), env| {
            let out = (p + env.physics_ns, s + env.step_ns);
            (env.physics_ns, env.step_ns) = (0, 0);
            out
        });
        let physics_share = if step_ns > 0 {
            physics_ns as f64 / step_ns as f64
        } else {
            0.0
        };
        self.times.physics_s += parallel_s * physics_share;
        self.times.task_s += parallel_s * (1.0 - physics_share);
        let rest_start = Instant::now();
        b.risk_exceeded = [0; NUM_RISK_TERMS];
        b.risk_fired = [0; NUM_RISK_TERMS];
        b.pushes = 0;
        for (i, env) in self.envs.iter_mut().enumerate() {
            let res = env.last_step;
            for k in 0..NUM_RISK_TERMS {
                b.risk_exceeded[k] += res.risk.exceeded[k] as u64;
                b.risk_fired[k] += res.risk.fired[k] as u64;
            }
            b.pushes += res.pushed as u64;
            if let Some(s) = env.take_summary() {
                // The curriculum sees the episode before the env resets onto its next tile.
                if let Some(c) = &mut self.curriculum {
                    c.update(i, s.distance_m, s.commanded_distance_m);
                    env.set_terrain_cell(c.level(i), c.terrain_type(i));
                }
                self.episodes.push(s);
            }
        }
        // Auto-reset, in parallel: each env draws from its own RNG, so the order
        // (and the thread count) does not change the result.
        let obs = &mut b.obs;
        self.pool.install(|| {
            self.envs
                .par_iter_mut()
                .zip(obs.par_chunks_mut(width))
                .filter(|(env, _)| env.last_step.done)
                .for_each(|(env, o)| {
                    if env.reset(o).is_err() {
                        env.instabilities += 1;
                    }
                });
        });
        self.times.reset_s += rest_start.elapsed().as_secs_f64();
        &self.batch
    }

    /// Step time split since the last call (and resets it).
    pub fn take_times(&mut self) -> StepTimes {
        std::mem::take(&mut self.times)
    }

    /// Episodes that finished since the last call.
    pub fn drain_episodes(&mut self) -> std::vec::Drain<'_, EpisodeSummary> {
        self.episodes.drain(..)
    }

    /// Total physics failures over all envs.
    pub fn instabilities(&self) -> u64 {
        self.envs.iter().map(|e| e.instabilities).sum()
    }

    /// Every env's terrain level (`None` on flat ground), for checkpoints.
    pub fn terrain_levels(&self) -> Option<Vec<usize>> {
        self.curriculum.as_ref().map(|c| c.levels().to_vec())
    }

    /// Restores stored terrain levels (a resumed run continues its curriculum)
    /// and restarts every env on its tile.
    pub fn restore_terrain_levels(&mut self, levels: &[usize]) -> Result<()> {
        let c = self.curriculum.as_mut().ok_or_else(|| {
            SimError::Invalid("terrain levels stored but this run has no terrain".into())
        })?;
        c.restore_levels(levels).map_err(SimError::Invalid)?;
        self.sync_terrain_cells();
        self.reset_all()
    }

    /// The most of MuJoCo's arena (contacts, constraint rows, stack) any env
    /// has used so far, beside the capacity.
    pub fn max_arena_use(&self) -> ArenaUse {
        self.envs
            .iter()
            .map(|e| e.arena_use())
            .reduce(ArenaUse::max)
            .unwrap_or_default()
    }

    /// Every env's episode state and the curriculum, as bytes, between two
    /// steps: with the runner's current observations, what a resumed run needs
    /// to continue every episode bit for bit ([`VecEnv::restore_snapshot`]).
    pub fn snapshot(&self) -> Vec<u8> {
        let mut w = StateWriter::new(VEC_ENV_SNAPSHOT_TAG);
        w.usize(self.envs.len());
        w.usize(self.obs_width);
        w.u64(self.curriculum.is_some() as u64);
        if let Some(c) = &self.curriculum {
            c.snapshot(&mut w);
        }
        for env in &self.envs {
            env.snapshot(&mut w);
        }
        w.into_bytes()
    }

    /// Restores [`VecEnv::snapshot`] of envs of the same config and count.
    pub fn restore_snapshot(&mut self, bytes: &[u8]) -> anyhow::Result<()> {
        let mut r = StateReader::new(bytes, VEC_ENV_SNAPSHOT_TAG)?;
        let (n, width) = (r.usize()?, r.usize()?);
        anyhow::ensure!(
            n == self.envs.len() && width == self.obs_width,
            "a snapshot of {n} envs x {width} observations for {} envs x {}",
            self.envs.len(),
            self.obs_width
        );
        let has_curriculum = r.u64()? != 0;
        anyhow::ensure!(
            has_curriculum == self.curriculum.is_some(),
            "the snapshot and this run differ in having a terrain curriculum"
        );
        if let Some(c) = &mut self.curriculum {
            c.restore(&mut r)?;
        }
        for env in &mut self.envs {
            env.restore(&mut r)?;
        }
        r.finish()
    }

    /// Mean terrain level over envs (0 on flat ground).
    pub fn mean_terrain_level(&self) -> f64 {
        self.curriculum.as_ref().map_or(0.0, |c| c.mean_level())
    }
}
