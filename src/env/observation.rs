//! The 48-float proprioceptive observation (legged_gym layout and scales).

use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use super::config::ObservationConfig;
use super::state::RobotState;
use crate::robot::NUM_JOINTS;

/// Observation length.
pub const OBS_DIM: usize = 48;
/// Action length.
pub const ACT_DIM: usize = NUM_JOINTS;

/// (name, length) of each observation group, in order. Saved in checkpoints so a
/// policy is never run on a differently laid out observation.
pub const OBS_LAYOUT: [(&str, usize); 7] = [
    ("base_lin_vel_body", 3),
    ("base_ang_vel_body", 3),
    ("gravity_body", 3),
    ("command_vx_vy_yaw", 3),
    ("joint_pos_minus_default", 12),
    ("joint_vel", 12),
    ("previous_action", 12),
];

/// The layout as one string, e.g. for checkpoint metadata.
pub fn layout_string() -> String {
    OBS_LAYOUT
        .iter()
        .map(|(n, k)| format!("{n}:{k}"))
        .collect::<Vec<_>>()
        .join(",")
}

/// Writes the observation into `out` (length [`OBS_DIM`]). Noise (Gaussian, std
/// per group in physical units times the group's scale) is drawn from `rng`
/// when given; commands and actions are never noised.
pub fn write_observation<R: Rng>(
    state: &RobotState,
    command: &[f64; 3],
    previous_action: &[f32],
    default_q_rad: &[f64; NUM_JOINTS],
    cfg: &ObservationConfig,
    mut rng: Option<&mut R>,
    out: &mut [f32],
) {
    let s = &cfg.scales;
    let n = &cfg.noise_std;
    let level = cfg.noise_level;
    let mut i = 0;
    let mut put = |value: f64, scale: f64, noise_std: f64, rng: &mut Option<&mut R>| {
        let mut v = value * scale;
        if let Some(r) = rng.as_deref_mut() {
            if noise_std > 0.0 && level > 0.0 {
                let z: f64 = r.sample(StandardNormal);
                v += z * noise_std * level * scale;
            }
        }
        out[i] = v.clamp(-cfg.clip, cfg.clip) as f32;
        i += 1;
    };
    for &v in &state.base_lin_vel_body_mps {
        put(v, s.lin_vel, n.lin_vel, &mut rng);
    }
    for &w in &state.base_ang_vel_body_rad_s {
        put(w, s.ang_vel, n.ang_vel, &mut rng);
    }
    for &g in &state.gravity_body {
        put(g, s.gravity, n.gravity, &mut rng);
    }
    for (&c, &scale) in command.iter().zip(&cfg.command_scale) {
        put(c, scale, 0.0, &mut rng);
    }
    for (&q, &q0) in state.q_rad.iter().zip(default_q_rad) {
        put(q - q0, s.dof_pos, n.dof_pos, &mut rng);
    }
    for &qd in &state.qd_rad_s {
        put(qd, s.dof_vel, n.dof_vel, &mut rng);
    }
    for &a in &previous_action[..NUM_JOINTS] {
        put(a as f64, 1.0, 0.0, &mut rng);
    }
    debug_assert_eq!(i, OBS_DIM);
}

/// A named block of the observation row. The env writes the groups its config
/// lists, in that order; which group feeds which network is the learner's
/// configuration (`actor_inputs`, `critic_inputs`, `encoder`, `adaptation`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ObsGroup {
    /// The paper's 48 proprioceptive values (what the robot measures).
    Policy,
    /// What a teacher may know: this episode's randomised parameters, the push
    /// in effect, the true base velocity and the ground under the feet.
    Privileged,
    /// RMA's environment factors e_t alone: the episode's friction, added mass,
    /// centre of mass, motor strengths and PD factors (the first 19 values of
    /// `privileged`), constant over an episode.
    Extrinsics,
    /// The last `history_steps` policy observations, newest first (each holds
    /// the action before it), zeros before the episode's first step.
    History,
}

impl ObsGroup {
    pub fn name(self) -> &'static str {
        match self {
            ObsGroup::Policy => "policy",
            ObsGroup::Privileged => "privileged",
            ObsGroup::Extrinsics => "extrinsics",
            ObsGroup::History => "history",
        }
    }

    /// Values in this group.
    pub fn width(self, history_steps: usize) -> usize {
        match self {
            ObsGroup::Policy => OBS_DIM,
            ObsGroup::Privileged => super::privileged::PRIVILEGED_DIM,
            ObsGroup::Extrinsics => super::privileged::EXTRINSICS_DIM,
            ObsGroup::History => history_steps * OBS_DIM,
        }
    }

    /// Field names, widths and scales, for checkpoints and exports.
    pub fn fields_string(self, history_steps: usize) -> String {
        match self {
            ObsGroup::Policy => layout_string(),
            ObsGroup::Privileged => super::privileged::layout_string(),
            ObsGroup::Extrinsics => super::privileged::extrinsics_layout_string(),
            ObsGroup::History => format!("{history_steps}x[policy, newest first]"),
        }
    }
}

/// The observation layout an env config produces.
pub fn obs_layout(cfg: &ObservationConfig) -> crate::learn::ObsLayout {
    crate::learn::ObsLayout::from_groups(
        cfg.groups
            .iter()
            .map(|g| (g.name().to_string(), g.width(cfg.history_steps)))
            .collect(),
    )
}
