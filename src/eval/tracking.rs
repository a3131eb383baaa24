//! `rall eval tracking`: how well a policy follows random velocity commands on
//! flat ground, with the observation noise and PD of training.

use std::sync::Arc;

use anyhow::Result;
use rand::SeedableRng;

use crate::env::config::PushConfig;
use crate::env::terrain::TerrainKind;
use crate::env::{build_scene, EnvConfig, EpisodeEnd, VecEnv};
use crate::learn::Learner;

/// Tracking figures over all evaluated episodes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackingReport {
    pub episodes: usize,
    /// Mean over robot-steps of exp(-|v_cmd_xy - v_xy|^2 / sigma), in [0, 1].
    pub lin_vel_score: f64,
    /// Mean over robot-steps of exp(-(w_cmd - w_z)^2 / sigma), in [0, 1].
    pub yaw_rate_score: f64,
    /// Fraction of episodes that ended before the time-out.
    pub fall_rate: f64,
    pub mean_episode_length_steps: f64,
    pub max_episode_length_steps: usize,
    /// Episodes ended by trunk contact, by tilt, by physics failure.
    pub trunk_contacts: usize,
    pub tilts: usize,
    pub unstable: usize,
}

/// The training env config made into the tracking benchmark: flat ground, no
/// pushes (commands, noise, PD, friction and mass randomisation as in training).
pub fn tracking_env(training: &EnvConfig) -> EnvConfig {
    let mut cfg = training.clone();
    cfg.terrain.kind = TerrainKind::Flat;
    cfg.randomization.push = PushConfig::None;
    cfg.episode.randomize_initial_length = false;
    cfg
}

/// How the policy picks actions during evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ActionMode {
    /// The Gaussian's mean (deployment).
    Mean,
    /// Sampled as in training, from a generator seeded with `seed`.
    Sampled,
}

/// Runs `episodes` robots in parallel for one full episode each.
pub fn evaluate_tracking(
    learner: &Learner,
    env_cfg: &EnvConfig,
    episodes: usize,
    threads: usize,
    seed: u64,
    mode: ActionMode,
) -> Result<TrackingReport> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let scene = build_scene(env_cfg, seed)?;
    let cfg = Arc::new(env_cfg.clone());
    let sigma = cfg.reward.tracking_sigma;
    let mut envs = VecEnv::new(cfg.clone(), &scene.model, None, episodes, threads, seed)?;
    let max_steps = cfg.max_episode_steps();
    let mut alive = vec![true; episodes];
    envs.drain_episodes().for_each(drop);
    let (mut lin_sum, mut yaw_sum, mut samples) = (0.0, 0.0, 0usize);
    let mut obs = envs.batch().obs.clone();
    for _ in 0..max_steps {
        let actions = match mode {
            ActionMode::Mean => learner.act_mean(&obs),
            ActionMode::Sampled => learner.act(&obs, &mut rng).actions,
        };
        // Score the command each robot followed during this step.
        let commands: Vec<[f64; 3]> = envs.envs().iter().map(|e| e.command()).collect();
        let b = envs.step(&actions);
        obs.copy_from_slice(&b.obs);
        let done = b.dones.clone();
        for (i, env) in envs.envs().iter().enumerate() {
            if !alive[i] {
                continue;
            }
            if done[i] {
                alive[i] = false;
                continue;
            }
            let s = env.state();
            let c = commands[i];
            let v = s.base_lin_vel_body_mps;
            let lin_err = (c[0] - v[0]).powi(2) + (c[1] - v[1]).powi(2);
            let yaw_err = (c[2] - s.base_ang_vel_body_rad_s[2]).powi(2);
            lin_sum += (-lin_err / sigma).exp();
            yaw_sum += (-yaw_err / sigma).exp();
            samples += 1;
        }
        if alive.iter().all(|a| !a) {
            break;
        }
    }
    // Only each robot's first episode counts.
    let mut first = vec![None; episodes];
    for e in envs.drain_episodes() {
        if first[e.env_index].is_none() {
            first[e.env_index] = Some(e);
        }
    }
    let lengths: Vec<(usize, bool)> = first
        .iter()
        .map(|e| {
            e.map_or((max_steps, false), |e| {
                (e.steps, e.end != EpisodeEnd::TimeOut)
            })
        })
        .collect();
    let ended = |end: EpisodeEnd| first.iter().flatten().filter(|e| e.end == end).count();
    let n = episodes.max(1) as f64;
    Ok(TrackingReport {
        episodes,
        lin_vel_score: if samples > 0 {
            lin_sum / samples as f64
        } else {
            0.0
        },
        yaw_rate_score: if samples > 0 {
            yaw_sum / samples as f64
        } else {
            0.0
        },
        fall_rate: lengths.iter().filter(|(_, fell)| *fell).count() as f64 / n,
        mean_episode_length_steps: lengths.iter().map(|(l, _)| *l as f64).sum::<f64>() / n,
        max_episode_length_steps: max_steps,
        trunk_contacts: ended(EpisodeEnd::TrunkContact),
        tilts: ended(EpisodeEnd::Tilt),
        unstable: ended(EpisodeEnd::Unstable),
    })
}
