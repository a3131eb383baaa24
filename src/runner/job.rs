//! The job across MPI ranks: one stop decision, one sum of each iteration's
//! statistics, rank 0's learner state on every rank, a check that the ranks
//! still hold the same parameters, and checkpoints with every rank's state.
//! Alone (one process) each of these is the identity.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{Context, Result};
use rand_chacha::ChaCha8Rng;

use super::checkpoint_kinds::Progress;
use super::dist::{diverged_ranks, hash_f32, World};
use super::metrics::EpisodeStats;
use super::resume::gather_rank_states;
use super::run_dir::{save_both, RunDir};
use crate::config::TrainConfig;
use crate::env::risk::NUM_RISK_TERMS;
use crate::env::VecEnv;
use crate::learn::{Collective, Learner};

/// Iterations between two comparisons of the ranks' learner state (MPI).
pub const PARAM_CHECK_INTERVAL: usize = 10;

/// Whether any rank was asked to stop: all of them stop at the same iteration.
pub(super) fn any_rank_stopped(world: &World, stop: &AtomicBool) -> bool {
    let mut stop_votes = [stop.load(Ordering::SeqCst) as u8 as f64];
    world.sum_f64(&mut stop_votes);
    stop_votes[0] > 0.0
}

/// One iteration's statistics summed (means: averaged) over every rank.
pub(super) struct JobIteration {
    pub episodes: EpisodeStats,
    pub risk_exceeded: [u64; NUM_RISK_TERMS],
    pub risk_fired: [u64; NUM_RISK_TERMS],
    pub terrain_level: f64,
    pub instabilities: [u64; 2],
}

impl JobIteration {
    /// One sum across ranks of everything the metrics row reports.
    pub(super) fn reduce(
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

/// Rank 0's learner state (weights, Adam moments, step, lr) on every rank.
pub(super) fn broadcast_learner_state(world: &World, learner: &mut Learner) -> Result<()> {
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
pub(super) fn check_same_state(world: &World, learner: &Learner, iteration: usize) -> Result<()> {
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

/// Writes the checkpoints (rank 0) with every rank's terrain levels.
pub(super) fn save_job_checkpoint(
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
