//! Risk penalties (paper eq. 2, table II): each exceeded threshold is penalised
//! with probability p, so the penalty barely moves the mean return but shapes
//! the lower tail of the return distribution.

use rand::Rng;

use super::config::{RiskConfig, RiskTerm};
use super::state::RobotState;
use crate::robot::NUM_JOINTS;

/// One risk term: its name, what it measures, and its threshold and weight in the config.
pub struct RiskTermDef {
    pub name: &'static str,
    pub measure: fn(&RobotState) -> f64,
    pub setting: fn(&RiskConfig) -> RiskTerm,
    /// Joint terms: the per-joint quantity (its absolute value is compared with
    /// `RiskTerm::per_joint` when the config sets it).
    pub per_joint: Option<fn(&RobotState) -> &[f64; NUM_JOINTS]>,
}

pub const NUM_RISK_TERMS: usize = 5;

/// The paper's table II, one entry per term.
pub const RISK_TERMS: [RiskTermDef; NUM_RISK_TERMS] = [
    RiskTermDef {
        name: "base_pitch",
        measure: |s| s.pitch_rad.abs(),
        setting: |c| c.base_pitch,
        per_joint: None,
    },
    RiskTermDef {
        name: "base_roll",
        measure: |s| s.roll_rad.abs(),
        setting: |c| c.base_roll,
        per_joint: None,
    },
    RiskTermDef {
        name: "joint_velocity",
        measure: |s| max_abs(&s.qd_rad_s),
        setting: |c| c.joint_velocity,
        per_joint: Some(|s| &s.qd_rad_s),
    },
    RiskTermDef {
        name: "joint_acceleration",
        measure: |s| max_abs(&s.qdd_rad_s2),
        setting: |c| c.joint_acceleration,
        per_joint: Some(|s| &s.qdd_rad_s2),
    },
    RiskTermDef {
        name: "joint_torque",
        measure: |s| max_abs(&s.torques_nm),
        setting: |c| c.joint_torque,
        per_joint: Some(|s| &s.torques_nm),
    },
];

/// Names in [`RISK_TERMS`] order.
pub const RISK_TERM_NAMES: [&str; NUM_RISK_TERMS] = {
    let mut names = [""; NUM_RISK_TERMS];
    let mut i = 0;
    while i < NUM_RISK_TERMS {
        names[i] = RISK_TERMS[i].name;
        i += 1;
    }
    names
};

fn max_abs(xs: &[f64]) -> f64 {
    xs.iter().fold(0.0f64, |m, v| m.max(v.abs()))
}

/// The measured quantity of each risk term, in [`RISK_TERMS`] order.
pub fn risk_measures(s: &RobotState) -> [f64; NUM_RISK_TERMS] {
    std::array::from_fn(|i| (RISK_TERMS[i].measure)(s))
}

/// What the risk terms did in one step.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RiskOutcome {
    pub exceeded: [bool; NUM_RISK_TERMS],
    pub fired: [bool; NUM_RISK_TERMS],
    /// Sum of the fired weights (a positive number, subtracted from the reward).
    pub penalty: f64,
}

/// Which risk terms' thresholds `s` passes (per joint where the config sets them).
pub fn risk_crossings(s: &RobotState, cfg: &RiskConfig) -> [bool; NUM_RISK_TERMS] {
    let measures = risk_measures(s);
    std::array::from_fn(|i| {
        let def = &RISK_TERMS[i];
        let term = (def.setting)(cfg);
        match (term.per_joint, def.per_joint) {
            (Some(limits), Some(quantity)) => quantity(s)
                .iter()
                .zip(&limits)
                .any(|(x, limit)| x.abs() > *limit),
            _ => measures[i] > term.threshold,
        }
    })
}

/// r_risk = sum_i w_i * 1[s_i > s_bar_i] * B_p  (paper eq. 2).
pub fn evaluate_risk<R: Rng>(s: &RobotState, cfg: &RiskConfig, rng: &mut R) -> RiskOutcome {
    let mut out = RiskOutcome {
        exceeded: risk_crossings(s, cfg),
        ..Default::default()
    };
    for (i, def) in RISK_TERMS.iter().enumerate() {
        // Draw only when exceeded: the stream of draws is the same whatever p is.
        if out.exceeded[i] && rng.gen::<f64>() < cfg.probability {
            out.fired[i] = true;
            out.penalty += (def.setting)(cfg).weight;
        }
    }
    out
}
