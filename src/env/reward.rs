//! The task reward (paper table I), one named term at a time.

use super::config::RewardConfig;
use super::state::RobotState;
use crate::robot::NUM_JOINTS;

/// Number of task reward terms.
pub const NUM_REWARD_TERMS: usize = 11;
/// Names of the terms in [`RewardTerms::as_array`] order.
pub const REWARD_TERM_NAMES: [&str; NUM_REWARD_TERMS] = [
    "lin_vel_tracking",
    "ang_vel_tracking",
    "lin_vel_z",
    "ang_vel_xy",
    "joint_acc",
    "torques",
    "action_magnitude",
    "collision",
    "action_rate",
    "torque_rate",
    "feet_air_time",
];

/// Each term already multiplied by its weight and the policy dt.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RewardTerms(pub [f64; NUM_REWARD_TERMS]);

impl RewardTerms {
    pub fn as_array(&self) -> &[f64; NUM_REWARD_TERMS] {
        &self.0
    }
    pub fn sum(&self) -> f64 {
        self.0.iter().sum()
    }
}

/// What the reward needs beyond the current state.
pub struct RewardInputs<'a> {
    pub state: &'a RobotState,
    /// Torques of the previous policy step (N m).
    pub previous_torques_nm: &'a [f64; NUM_JOINTS],
    pub action: &'a [f32],
    pub previous_action: &'a [f32],
    /// (vx m/s, vy m/s, yaw rate rad/s).
    pub command: &'a [f64; 3],
    /// Air time (s) of each foot that touched down this step (0 when it did not).
    pub touchdown_air_time_s: &'a [f64; 4],
}

fn sum_sq(it: impl Iterator<Item = f64>) -> f64 {
    it.map(|v| v * v).sum()
}

/// Unweighted terms, in [`REWARD_TERM_NAMES`] order.
pub fn raw_terms(x: &RewardInputs, cfg: &RewardConfig) -> [f64; NUM_REWARD_TERMS] {
    let s = x.state;
    let v = s.base_lin_vel_body_mps;
    let w = s.base_ang_vel_body_rad_s;
    let lin_err = (x.command[0] - v[0]).powi(2) + (x.command[1] - v[1]).powi(2);
    let yaw_err = (x.command[2] - w[2]).powi(2);
    let moving = (x.command[0].powi(2) + x.command[1].powi(2)).sqrt() > 0.1;
    let air: f64 = x
        .touchdown_air_time_s
        .iter()
        .filter(|&&t| t > 0.0)
        .map(|&t| t - cfg.feet_air_time_target_s)
        .sum();
    [
        (-lin_err / cfg.tracking_sigma).exp(),
        (-yaw_err / cfg.tracking_sigma).exp(),
        v[2] * v[2],
        w[0] * w[0] + w[1] * w[1],
        sum_sq(s.qdd_rad_s2.iter().copied()),
        sum_sq(s.torques_nm.iter().copied()),
        sum_sq(x.action.iter().map(|&a| a as f64)),
        s.penalised_contacts as f64,
        sum_sq(
            x.action
                .iter()
                .zip(x.previous_action)
                .map(|(&a, &b)| (a - b) as f64),
        ),
        sum_sq(
            s.torques_nm
                .iter()
                .zip(x.previous_torques_nm)
                .map(|(a, b)| a - b),
        ),
        if moving { air } else { 0.0 },
    ]
}

/// The weighted, dt-scaled terms.
pub fn reward_terms(x: &RewardInputs, cfg: &RewardConfig, policy_dt_s: f64) -> RewardTerms {
    let raw = raw_terms(x, cfg);
    let weights = [
        cfg.lin_vel_tracking,
        cfg.ang_vel_tracking,
        cfg.lin_vel_z,
        cfg.ang_vel_xy,
        cfg.joint_acc,
        cfg.torques,
        cfg.action_magnitude,
        cfg.collision,
        cfg.action_rate,
        cfg.torque_rate,
        cfg.feet_air_time,
    ];
    RewardTerms(std::array::from_fn(|i| raw[i] * weights[i] * policy_dt_s))
}
