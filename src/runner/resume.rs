//! The runner's share of an exact resume: per rank, its envs' episodes and
//! RNGs ([`VecEnv::snapshot`]), the observations the policy acts on next and
//! the last episode statistics the metrics repeat. With the learner's exact
//! state and the action RNG's position (in [`Progress`]), a run resumed from a
//! checkpoint continues bit for bit as if it had never stopped.

use std::sync::Arc;

use anyhow::{Context, Result};

use super::dist::{rank_seed, World};
use super::metrics::EpisodeStats;
use super::Progress;
use crate::config::TrainConfig;
use crate::env::snapshot::{StateReader, StateWriter};
use crate::env::{Scene, VecEnv};
use rand_chacha::ChaCha8Rng;

const RUNNER_STATE_TAG: &str = "rall-runner-1";

/// One rank's runner state as bytes (`action_rng`: the action-noise RNG of
/// PPO's collection; ranks draw different amounts from theirs).
pub(super) fn encode_rank_state(
    envs: &VecEnv,
    obs: &[f32],
    last: &EpisodeStats,
    action_rng: Option<&ChaCha8Rng>,
) -> Vec<u8> {
    let mut w = StateWriter::new(RUNNER_STATE_TAG);
    w.u64(action_rng.is_some() as u64);
    if let Some(r) = action_rng {
        w.rng(r);
    }
    w.f32s(obs);
    w.usize(last.episodes);
    w.usize(last.falls);
    w.f64s(&[
        last.mean_return,
        last.mean_length_steps,
        last.lin_tracking_score,
    ]);
    w.f64s(&last.reward_terms);
    w.bytes(&envs.snapshot());
    w.into_bytes()
}

/// Restores [`encode_rank_state`] into `start` (envs built from the same config).
fn decode_rank_state(bytes: &[u8], start: &mut RankStart) -> Result<()> {
    let mut r = StateReader::new(bytes, RUNNER_STATE_TAG)?;
    if r.u64()? != 0 {
        start.action_rng = Some(r.rng()?);
    }
    let (envs, obs, last) = (&mut start.envs, &mut start.obs, &mut start.last_stats);
    r.f32s_into(obs, "observations")?;
    last.episodes = r.usize()?;
    last.falls = r.usize()?;
    let mut means = [0.0; 3];
    r.f64s_into(&mut means, "episode means")?;
    [
        last.mean_return,
        last.mean_length_steps,
        last.lin_tracking_score,
    ] = means;
    r.f64s_into(&mut last.reward_terms, "reward terms")?;
    envs.restore_snapshot(r.bytes()?)?;
    r.finish()
}

/// Every rank's runner state, in rank order, on rank 0 (empty elsewhere).
pub(super) fn gather_rank_states(
    world: &World,
    envs: &VecEnv,
    obs: &[f32],
    last: &EpisodeStats,
    action_rng: &ChaCha8Rng,
) -> Result<Vec<Vec<u8>>> {
    world.gather_bytes(&encode_rank_state(envs, obs, last, Some(action_rng)))
}

/// A rank's envs at the start of a (resumed) run.
pub(super) struct RankStart {
    pub envs: VecEnv,
    /// The observations the policy acts on first.
    pub obs: Vec<f32>,
    /// The last iteration's episode statistics (metrics repeat them when an
    /// iteration ends no episode).
    pub last_stats: EpisodeStats,
    /// The seed the envs were built from (RMA's phase 2 derives its envs from it).
    pub env_seed: u64,
    /// The action-noise RNG as stored (exact resume only).
    pub action_rng: Option<ChaCha8Rng>,
}

/// This rank's stored state when the checkpoint allows an exact resume by
/// `ranks` ranks, else why not (for the one-line note).
pub(super) fn exact_state(
    progress: &Progress,
    learner_exact: bool,
    rank: usize,
    ranks: usize,
) -> std::result::Result<Vec<u8>, String> {
    let stored = progress.rank_states.len();
    if !learner_exact || stored == 0 {
        return Err("it predates checkpoints that hold the envs' episodes and RNG states".into());
    }
    if stored != ranks {
        return Err(format!(
            "it was written by {stored} rank(s), this job has {ranks}"
        ));
    }
    Ok(progress.rank_states[rank].clone())
}

/// This rank's envs: continued from `exact` (a stored runner state), else
/// fresh episodes on the checkpoint's curriculum levels.
pub(super) fn start_envs(
    cfg: &TrainConfig,
    scene: &Scene,
    threads: usize,
    rank: usize,
    progress: &Progress,
    exact: Option<&[u8]>,
) -> Result<RankStart> {
    let r = &cfg.runner;
    // Without a stored state, envs restart fresh episodes, seeded by the
    // iteration so a resumed run does not replay the first run's episodes.
    let offset = match exact {
        Some(_) => 0,
        None => (progress.iteration as u64).wrapping_mul(0x9E37_79B9),
    };
    let env_seed = rank_seed(r.seed.wrapping_add(offset), rank);
    let mut envs = VecEnv::new(
        Arc::new(cfg.env.clone()),
        &scene.model,
        scene.terrain.clone(),
        r.num_envs,
        threads,
        env_seed,
    )?;
    if let Some(bytes) = exact {
        let mut start = RankStart {
            obs: envs.batch().obs.clone(),
            envs,
            last_stats: EpisodeStats::default(),
            env_seed,
            action_rng: None,
        };
        decode_rank_state(bytes, &mut start)
            .context("restoring the envs' episodes from the checkpoint")?;
        return Ok(start);
    }
    if let Some(levels) = &progress.terrain_levels {
        envs.restore_terrain_levels(&rank_levels(levels, rank, r.num_envs))
            .context("restoring the terrain curriculum of the checkpoint")?;
    }
    if cfg.env.episode.randomize_initial_length {
        envs.randomize_episode_progress();
    }
    Ok(RankStart {
        obs: envs.batch().obs.clone(),
        envs,
        last_stats: EpisodeStats::default(),
        env_seed,
        action_rng: None,
    })
}

/// Rank `rank`'s terrain levels from a checkpoint's: its own slice when the
/// checkpoint holds every rank's (`ranks x num_envs`), else the stored levels
/// cycled (a checkpoint of another rank count).
fn rank_levels(stored: &[usize], rank: usize, num_envs: usize) -> Vec<usize> {
    if stored.is_empty() {
        return Vec::new();
    }
    (0..num_envs)
        .map(|i| stored[(rank * num_envs + i) % stored.len()])
        .collect()
}
