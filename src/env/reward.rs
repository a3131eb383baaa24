//! The task reward (paper table I), one named term at a time.

use super::config::RewardConfig;
use super::state::RobotState;
use crate::robot::NUM_JOINTS;

/// One task reward term: its name, its weight in the config, and what it
/// measures (unweighted). The reward is `sum_i weight_i * value_i * dt`.
pub struct RewardTerm {
    pub name: &'static str,
    pub weight: fn(&RewardConfig) -> f64,
    pub value: fn(&RewardInputs, &RewardConfig) -> f64,
}

/// Number of task reward terms.
pub const NUM_REWARD_TERMS: usize = 11;

/// The paper's table I, one entry per term.
pub const REWARD_TERMS: [RewardTerm; NUM_REWARD_TERMS] = [
    RewardTerm {
        name: "lin_vel_tracking",
        weight: |c| c.lin_vel_tracking,
        value: lin_vel_tracking,
    },
    RewardTerm {
        name: "ang_vel_tracking",
        weight: |c| c.ang_vel_tracking,
        value: ang_vel_tracking,
    },
    RewardTerm {
        name: "lin_vel_z",
        weight: |c| c.lin_vel_z,
        value: |x, _| x.state.base_lin_vel_body_mps[2].powi(2),
    },
    RewardTerm {
        name: "ang_vel_xy",
        weight: |c| c.ang_vel_xy,
        value: |x, _| sum_sq(x.state.base_ang_vel_body_rad_s[..2].iter().copied()),
    },
    RewardTerm {
        name: "joint_acc",
        weight: |c| c.joint_acc,
        value: |x, _| sum_sq(x.state.qdd_rad_s2.iter().copied()),
    },
    RewardTerm {
        name: "torques",
        weight: |c| c.torques,
        value: |x, _| sum_sq(x.state.torques_nm.iter().copied()),
    },
    RewardTerm {
        name: "action_magnitude",
        weight: |c| c.action_magnitude,
        value: |x, _| sum_sq(x.action.iter().map(|&a| a as f64)),
    },
    RewardTerm {
        name: "collision",
        weight: |c| c.collision,
        value: |x, _| x.state.penalised_contacts as f64,
    },
    RewardTerm {
        name: "action_rate",
        weight: |c| c.action_rate,
        value: |x, _| {
            sum_sq(
                x.action
                    .iter()
                    .zip(x.previous_action)
                    .map(|(&a, &b)| (a - b) as f64),
            )
        },
    },
    RewardTerm {
        name: "torque_rate",
        weight: |c| c.torque_rate,
        value: |x, _| {
            sum_sq(
                x.state
                    .torques_nm
                    .iter()
                    .zip(x.previous_torques_nm)
                    .map(|(a, b)| a - b),
            )
        },
    },
    RewardTerm {
        name: "feet_air_time",
        weight: |c| c.feet_air_time,
        value: feet_air_time,
    },
];

/// Names of the terms in [`REWARD_TERMS`] order.
pub const REWARD_TERM_NAMES: [&str; NUM_REWARD_TERMS] = {
    let mut names = [""; NUM_REWARD_TERMS];
    let mut i = 0;
    while i < NUM_REWARD_TERMS {
        names[i] = REWARD_TERMS[i].name;
        i += 1;
    }
    names
};

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

/// exp(-|v_cmd,xy - v_xy|^2 / sigma)
fn lin_vel_tracking(x: &RewardInputs, cfg: &RewardConfig) -> f64 {
    let v = x.state.base_lin_vel_body_mps;
    let err = (x.command[0] - v[0]).powi(2) + (x.command[1] - v[1]).powi(2);
    (-err / cfg.tracking_sigma).exp()
}

/// exp(-(w_cmd,yaw - w_yaw)^2 / sigma)
fn ang_vel_tracking(x: &RewardInputs, cfg: &RewardConfig) -> f64 {
    let err = (x.command[2] - x.state.base_ang_vel_body_rad_s[2]).powi(2);
    (-err / cfg.tracking_sigma).exp()
}

/// sum over feet touching down of (air time - target), only while commanded to move.
fn feet_air_time(x: &RewardInputs, cfg: &RewardConfig) -> f64 {
    let moving = (x.command[0].powi(2) + x.command[1].powi(2)).sqrt() > 0.1;
    if !moving {
        return 0.0;
    }
    x.touchdown_air_time_s
        .iter()
        .filter(|&&t| t > 0.0)
        .map(|&t| t - cfg.feet_air_time_target_s)
        .sum()
}

/// Unweighted terms, in [`REWARD_TERM_NAMES`] order.
pub fn raw_terms(x: &RewardInputs, cfg: &RewardConfig) -> [f64; NUM_REWARD_TERMS] {
    std::array::from_fn(|i| (REWARD_TERMS[i].value)(x, cfg))
}

/// The weighted, dt-scaled terms.
pub fn reward_terms(x: &RewardInputs, cfg: &RewardConfig, policy_dt_s: f64) -> RewardTerms {
    RewardTerms(std::array::from_fn(|i| {
        let t = &REWARD_TERMS[i];
        (t.value)(x, cfg) * (t.weight)(cfg) * policy_dt_s
    }))
}
