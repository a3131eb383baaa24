//! `rall eval tracking`: how well a policy follows random velocity commands on
//! flat ground, with the observation noise and PD of training.

use std::sync::Arc;

use anyhow::Result;
use rand::SeedableRng;

use super::policy::Actor;
use crate::env::config::{PushConfig, RandomizationConfig};
use crate::env::terrain::TerrainKind;
use crate::env::{build_scene, EnvConfig, EpisodeDraw, EpisodeEnd, VecEnv};

/// One robot's share of the tracking figures: the unit a bootstrap resamples.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct RobotTracking {
    /// Sums over the robot's scored steps of the two per-step scores.
    pub lin_score_sum: f64,
    pub yaw_score_sum: f64,
    pub scored_steps: usize,
    pub fell: bool,
}

/// Mean over robot-steps of the linear tracking score (0 without steps).
pub fn lin_vel_score(robots: &[RobotTracking]) -> f64 {
    step_mean(robots, |r| r.lin_score_sum)
}

/// Mean over robot-steps of the yaw-rate tracking score (0 without steps).
pub fn yaw_rate_score(robots: &[RobotTracking]) -> f64 {
    step_mean(robots, |r| r.yaw_score_sum)
}

/// Fraction of robots whose episode ended before the time-out.
pub fn fall_rate(robots: &[RobotTracking]) -> f64 {
    robots.iter().filter(|r| r.fell).count() as f64 / robots.len().max(1) as f64
}

fn step_mean(robots: &[RobotTracking], sum: impl Fn(&RobotTracking) -> f64) -> f64 {
    let steps: usize = robots.iter().map(|r| r.scored_steps).sum();
    if steps == 0 {
        return 0.0;
    }
    robots.iter().map(sum).sum::<f64>() / steps as f64
}

/// Tracking figures over all evaluated episodes.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
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
    /// Each robot's figures (the scores and fall rate above are their pooled means).
    pub robots: Vec<RobotTracking>,
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

/// The tracking benchmark under another config's randomisation (friction, mass, motors,
/// PD, centre of mass; never pushes): every method judged on the same ground, where
/// [`tracking_env`] judges each under its own training draws.
pub fn with_randomization(mut env: EnvConfig, from: &RandomizationConfig) -> EnvConfig {
    env.randomization = RandomizationConfig {
        push: PushConfig::None,
        ..from.clone()
    };
    env
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
    learner: &dyn Actor,
    env_cfg: &EnvConfig,
    episodes: usize,
    threads: usize,
    seed: u64,
    mode: ActionMode,
) -> Result<TrackingReport> {
    evaluate_tracking_with_falls(learner, env_cfg, episodes, threads, seed, mode).map(|(r, _)| r)
}

/// Steps before a fall over which [`FallRecord::steps_at_torque_limit`] counts.
pub const FALL_WINDOW_STEPS: usize = 25;

/// How one robot fell: the command it followed and its last state before the end.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FallRecord {
    pub env_index: usize,
    /// Policy steps the episode lasted.
    pub steps: usize,
    pub end: EpisodeEnd,
    /// (vx m/s, vy m/s, yaw rate rad/s) at the end.
    pub command: [f64; 3],
    /// Attitude at the last step before the end (rad; pitch > 0: nose down,
    /// roll > 0: right side down).
    pub roll_rad: f64,
    pub pitch_rad: f64,
    /// Base velocity (body frame, m/s) at that step.
    pub base_lin_vel_body_mps: [f64; 3],
    /// Feet on the ground at that step (FR, FL, RR, RL: the SDK's leg order).
    pub foot_contact: [bool; 4],
    /// Of the last [`FALL_WINDOW_STEPS`] steps, those with a motor at its torque limit.
    pub steps_at_torque_limit: usize,
    /// Steps the robot followed its last command before the end (the whole episode
    /// when the command never changed).
    pub steps_since_command_change: usize,
    /// The command before the last change (`None`: it never changed).
    pub previous_command: Option<[f64; 3]>,
    /// The episode's randomisation draws.
    pub draw: EpisodeDraw,
}

impl FallRecord {
    /// Which way the robot went over: the larger of pitch and roll at the end.
    pub fn direction(&self) -> &'static str {
        if self.pitch_rad.abs() >= self.roll_rad.abs() {
            if self.pitch_rad >= 0.0 {
                "nose down"
            } else {
                "nose up"
            }
        } else if self.roll_rad >= 0.0 {
            "right side down"
        } else {
            "left side down"
        }
    }

    /// CSV header of [`FallRecord::csv_row`].
    pub const CSV_HEADER: &'static str = "env,steps,end,direction,cmd_vx_mps,cmd_vy_mps,cmd_yaw_rate_rad_s,roll_rad,pitch_rad,vx_body_mps,vy_body_mps,vz_body_mps,contact_FR,contact_FL,contact_RR,contact_RL,steps_at_torque_limit_of_last_25,steps_since_command_change,prev_cmd_vx_mps,prev_cmd_vy_mps,prev_cmd_yaw_rate_rad_s,friction,added_base_mass_kg,motor_strength_min,motor_strength_mean,kp_factor,kd_factor,com_offset_x_m,com_offset_y_m,com_offset_z_m";

    pub fn csv_row(&self) -> String {
        let c = self.command;
        let v = self.base_lin_vel_body_mps;
        let f = self.foot_contact.map(|b| b as u8);
        let d = &self.draw;
        let strength_min = d
            .motor_strength
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min);
        let strength_mean = d.motor_strength.iter().sum::<f64>() / d.motor_strength.len() as f64;
        let prev = match self.previous_command {
            Some(p) => format!("{:.3},{:.3},{:.3}", p[0], p[1], p[2]),
            None => ",,".to_string(),
        };
        format!(
            "{},{},{:?},{},{:.3},{:.3},{:.3},{:.4},{:.4},{:.3},{:.3},{:.3},{},{},{},{},{},{},{},{},{:.3},{:.3},{:.3},{:.3},{:.3},{:.4},{:.4},{:.4}",
            self.env_index,
            self.steps,
            self.end,
            self.direction(),
            c[0],
            c[1],
            c[2],
            self.roll_rad,
            self.pitch_rad,
            v[0],
            v[1],
            v[2],
            f[0],
            f[1],
            f[2],
            f[3],
            self.steps_at_torque_limit,
            self.steps_since_command_change,
            prev,
            d.friction.map_or(String::new(), |x| format!("{x:.3}")),
            d.added_base_mass_kg,
            strength_min,
            strength_mean,
            d.kp_factor,
            d.kd_factor,
            d.com_offset_m[0],
            d.com_offset_m[1],
            d.com_offset_m[2]
        )
    }
}

/// [`evaluate_tracking`], plus how each robot that fell in its first episode fell.
pub fn evaluate_tracking_with_falls(
    learner: &dyn Actor,
    env_cfg: &EnvConfig,
    episodes: usize,
    threads: usize,
    seed: u64,
    mode: ActionMode,
) -> Result<(TrackingReport, Vec<FallRecord>)> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let scene = build_scene(env_cfg, seed)?;
    let cfg = Arc::new(env_cfg.clone());
    let sigma = cfg.reward.tracking_sigma;
    let mut envs = VecEnv::new(cfg.clone(), &scene.model, None, episodes, threads, seed)?;
    let max_steps = cfg.max_episode_steps();
    let mut alive = vec![true; episodes];
    envs.drain_episodes().for_each(drop);
    let mut robots = vec![RobotTracking::default(); episodes];
    let mut obs = envs.batch().obs.clone();
    let mut watch = FallWatch::new(episodes, env_cfg);
    for step in 0..max_steps {
        let actions = match mode {
            ActionMode::Mean => learner.actions(&obs)?,
            ActionMode::Sampled => {
                let gaussian = learner.learner().ok_or_else(|| {
                    anyhow::anyhow!("sampled actions need a checkpoint's Gaussian; an ONNX policy gives its mean only")
                })?;
                gaussian.act(&obs, &mut rng).actions
            }
        };
        // Score the command each robot followed during this step.
        let commands: Vec<[f64; 3]> = envs.envs().iter().map(|e| e.command()).collect();
        // a robot whose first episode has ended stands still from here on
        let b = envs.step_active(&actions, Some(&alive));
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
            score_step(&mut robots[i], commands[i], env.state(), sigma);
            watch.observe(i, step, commands[i], env);
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
    let falls = watch.falls(&first);
    Ok((tracking_report(robots, &first, max_steps), falls))
}

/// Adds one step's tracking scores exp(-err^2 / sigma) of command `c`.
pub(crate) fn score_step(
    robot: &mut RobotTracking,
    c: [f64; 3],
    s: &crate::env::state::RobotState,
    sigma: f64,
) {
    let v = s.base_lin_vel_body_mps;
    let lin_err = (c[0] - v[0]).powi(2) + (c[1] - v[1]).powi(2);
    let yaw_err = (c[2] - s.base_ang_vel_body_rad_s[2]).powi(2);
    robot.lin_score_sum += (-lin_err / sigma).exp();
    robot.yaw_score_sum += (-yaw_err / sigma).exp();
    robot.scored_steps += 1;
}

/// The report over the robots' first episodes (`first[i]`: robot i's, if it ended).
fn tracking_report(
    mut robots: Vec<RobotTracking>,
    first: &[Option<crate::env::EpisodeSummary>],
    max_steps: usize,
) -> TrackingReport {
    let episodes = robots.len();
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
    for (robot, (_, fell)) in robots.iter_mut().zip(&lengths) {
        robot.fell = *fell;
    }
    TrackingReport {
        episodes,
        lin_vel_score: lin_vel_score(&robots),
        yaw_rate_score: yaw_rate_score(&robots),
        fall_rate: fall_rate(&robots),
        mean_episode_length_steps: lengths.iter().map(|(l, _)| *l as f64).sum::<f64>() / n,
        max_episode_length_steps: max_steps,
        trunk_contacts: ended(EpisodeEnd::TrunkContact),
        tilts: ended(EpisodeEnd::Tilt),
        unstable: ended(EpisodeEnd::Unstable),
        robots,
    }
}

/// Each robot's last step as a fall record, completed (length, end, steps at
/// the torque limit) once the episode's end is known.
struct FallWatch {
    last: Vec<Option<FallRecord>>,
    /// Bit i: i steps back a motor was at its limit.
    at_limit: Vec<u32>,
    /// The command followed and the step it started.
    followed: Vec<Option<([f64; 3], usize)>>,
    /// The command before it.
    previous: Vec<Option<[f64; 3]>>,
    torque_limits_nm: Vec<f64>,
}

impl FallWatch {
    fn new(robots: usize, cfg: &EnvConfig) -> FallWatch {
        FallWatch {
            last: vec![None; robots],
            at_limit: vec![0u32; robots],
            followed: vec![None; robots],
            previous: vec![None; robots],
            torque_limits_nm: (0..crate::robot::NUM_JOINTS)
                .map(|j| cfg.control.torque_limit_nm(j))
                .collect(),
        }
    }

    /// Robot `i`'s state after `step`, following command `c`.
    fn observe(&mut self, i: usize, step: usize, c: [f64; 3], env: &crate::env::Env) {
        let s = env.state();
        let saturated = s
            .torques_nm
            .iter()
            .zip(&self.torque_limits_nm)
            .any(|(t, l)| t.abs() >= 0.99 * l);
        self.at_limit[i] =
            ((self.at_limit[i] << 1) | saturated as u32) & ((1 << FALL_WINDOW_STEPS) - 1);
        match self.followed[i] {
            Some((before, _)) if before == c => {}
            Some((before, _)) => {
                self.previous[i] = Some(before);
                self.followed[i] = Some((c, step));
            }
            None => self.followed[i] = Some((c, step)),
        }
        self.last[i] = Some(FallRecord {
            env_index: i,
            steps: 0,
            end: EpisodeEnd::TimeOut,
            command: c,
            roll_rad: s.roll_rad,
            pitch_rad: s.pitch_rad,
            base_lin_vel_body_mps: s.base_lin_vel_body_mps,
            foot_contact: s.foot_contact,
            steps_at_torque_limit: 0,
            steps_since_command_change: 0,
            previous_command: self.previous[i],
            draw: env.draw,
        });
    }

    /// The records of the robots whose first episode ended in a fall.
    fn falls(&self, first: &[Option<crate::env::EpisodeSummary>]) -> Vec<FallRecord> {
        first
            .iter()
            .flatten()
            .filter(|e| e.end != EpisodeEnd::TimeOut)
            .filter_map(|e| {
                self.last[e.env_index].map(|f| FallRecord {
                    steps: e.steps,
                    end: e.end,
                    steps_at_torque_limit: self.at_limit[e.env_index].count_ones() as usize,
                    steps_since_command_change: e.steps
                        - self.followed[e.env_index].map_or(0, |(_, from)| from.min(e.steps)),
                    ..f
                })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn common_randomization_replaces_the_draws_and_nothing_else() {
        let mut own = EnvConfig::default();
        own.randomization.friction = Some([0.25, 2.5]);
        own.randomization.kd_factor = Some([0.75, 1.25]);
        own.reward.ang_vel_tracking = 2.5;
        let mut from = RandomizationConfig {
            friction: Some([0.5, 1.5]),
            ..Default::default()
        };
        from.kd_factor = None;
        let env = with_randomization(tracking_env(&own), &from);
        assert_eq!(env.randomization.friction, Some([0.5, 1.5]));
        assert_eq!(env.randomization.kd_factor, None);
        assert_eq!(env.randomization.push, PushConfig::None, "pushes stay off");
        // everything but the randomisation is the policy's own tracking benchmark
        let mut rest = env.clone();
        rest.randomization = tracking_env(&own).randomization;
        assert_eq!(rest, tracking_env(&own));
    }

    #[test]
    fn scores_pool_robot_steps_and_falls_count_robots() {
        let robot = |lin: f64, steps: usize, fell: bool| RobotTracking {
            lin_score_sum: lin,
            yaw_score_sum: 0.5 * lin,
            scored_steps: steps,
            fell,
        };
        // a robot that fell early weighs by its steps, not as one robot
        let robots = [robot(90.0, 100, false), robot(1.0, 10, true)];
        assert!((lin_vel_score(&robots) - 91.0 / 110.0).abs() < 1e-12);
        assert!((yaw_rate_score(&robots) - 45.5 / 110.0).abs() < 1e-12);
        assert_eq!(fall_rate(&robots), 0.5);
        assert_eq!(lin_vel_score(&[]), 0.0);
        assert_eq!(fall_rate(&[]), 0.0);
    }
}
