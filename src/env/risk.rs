//! Risk penalties (paper eq. 2, table II): each exceeded threshold is penalised
//! with probability p, so the penalty barely moves the mean return but shapes
//! the lower tail of the return distribution.

use rand::Rng;

use super::config::RiskConfig;
use super::state::RobotState;

pub const NUM_RISK_TERMS: usize = 5;
pub const RISK_TERM_NAMES: [&str; NUM_RISK_TERMS] = [
    "base_pitch",
    "base_roll",
    "joint_velocity",
    "joint_acceleration",
    "joint_torque",
];

/// The measured quantity of each risk term, in [`RISK_TERM_NAMES`] order.
pub fn risk_measures(s: &RobotState) -> [f64; NUM_RISK_TERMS] {
    let max_abs = |xs: &[f64]| xs.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    [
        s.pitch_rad.abs(),
        s.roll_rad.abs(),
        max_abs(&s.qd_rad_s),
        max_abs(&s.qdd_rad_s2),
        max_abs(&s.torques_nm),
    ]
}

/// What the risk terms did in one step.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RiskOutcome {
    pub exceeded: [bool; NUM_RISK_TERMS],
    pub fired: [bool; NUM_RISK_TERMS],
    /// Sum of the fired weights (a positive number, subtracted from the reward).
    pub penalty: f64,
}

/// r_risk = sum_i w_i * 1[s_i > s_bar_i] * B_p  (paper eq. 2).
pub fn evaluate_risk<R: Rng>(s: &RobotState, cfg: &RiskConfig, rng: &mut R) -> RiskOutcome {
    let measures = risk_measures(s);
    let mut out = RiskOutcome::default();
    for (i, (_, term)) in cfg.terms().iter().enumerate() {
        if measures[i] > term.threshold {
            out.exceeded[i] = true;
            // Draw only when exceeded: the stream of draws is the same whatever p is.
            if rng.gen::<f64>() < cfg.probability {
                out.fired[i] = true;
                out.penalty += term.weight;
            }
        }
    }
    out
}
