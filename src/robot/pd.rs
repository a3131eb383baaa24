//! Joint-space PD control: the policy's action becomes joint torques.

use serde::{Deserialize, Serialize};

use super::layout::NUM_JOINTS;

/// Low-level control settings (paper: PD at 200 Hz, Kp 50, Kd 0.8, policy at 50 Hz).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ControlConfig {
    /// Physics time step (s), in [1e-4, 0.05]: finer steps make an episode
    /// millions of physics steps (1e-12 never finishes one), coarser ones run
    /// PD below 20 Hz.
    pub physics_dt_s: f64,
    /// Physics steps per policy step (4 -> 50 Hz policy at dt 0.005),
    /// 1..=1000, with the policy step (`physics_dt_s x decimation`) at most 0.5 s.
    pub decimation: usize,
    /// Proportional gain (N m / rad), in (0, 1e6].
    pub kp_nm_per_rad: f64,
    /// Derivative gain (N m s / rad), in [0, 1e6].
    pub kd_nm_s_per_rad: f64,
    /// q_target = q_default + action_scale * action (rad per unit action), in (0, 100].
    pub action_scale_rad: f64,
    /// Actions are clipped to [-clip, clip] before scaling, clip in (0, 1e6].
    pub clip_actions: f64,
    /// Torque limits (N m) of hip, thigh, calf motors, each in (0, 1e4].
    pub torque_limits_nm: [f64; 3],
    /// Keyframe holding the default joint angles and the initial base pose.
    pub default_keyframe: String,
}

impl Default for ControlConfig {
    fn default() -> Self {
        ControlConfig {
            physics_dt_s: 0.005,
            decimation: 4,
            kp_nm_per_rad: 50.0,
            kd_nm_s_per_rad: 0.8,
            action_scale_rad: 0.25,
            clip_actions: 100.0,
            torque_limits_nm: [44.0, 44.0, 55.0],
            default_keyframe: "stand".into(),
        }
    }
}

/// Finest physics step a config may set (s).
pub const MIN_PHYSICS_DT_S: f64 = 1e-4;
/// Coarsest physics step a config may set (s).
pub const MAX_PHYSICS_DT_S: f64 = 0.05;
/// Longest policy step a config may set (s).
pub const MAX_POLICY_DT_S: f64 = 0.5;

impl ControlConfig {
    /// Policy period (s).
    pub fn policy_dt_s(&self) -> f64 {
        self.physics_dt_s * self.decimation as f64
    }

    /// Refuses values that cannot work, naming the key.
    pub fn validate(&self) -> Result<(), String> {
        let positive = [
            ("control.physics_dt_s", self.physics_dt_s),
            ("control.kp_nm_per_rad", self.kp_nm_per_rad),
            ("control.action_scale_rad", self.action_scale_rad),
            ("control.clip_actions", self.clip_actions),
        ];
        for (key, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{key} must be a positive number, got {v}"));
            }
        }
        if !(self.kd_nm_s_per_rad.is_finite() && self.kd_nm_s_per_rad >= 0.0) {
            return Err(format!(
                "control.kd_nm_s_per_rad must be >= 0, got {}",
                self.kd_nm_s_per_rad
            ));
        }
        if !(1..=1000).contains(&self.decimation) {
            return Err(format!(
                "control.decimation must be in 1..=1000, got {}",
                self.decimation
            ));
        }
        if !(MIN_PHYSICS_DT_S..=MAX_PHYSICS_DT_S).contains(&self.physics_dt_s) {
            return Err(format!(
                "control.physics_dt_s must be in [{MIN_PHYSICS_DT_S}, {MAX_PHYSICS_DT_S}] s, got {}: a finer step makes an episode millions of physics steps, a coarser one runs PD below 20 Hz",
                self.physics_dt_s
            ));
        }
        if self.policy_dt_s() > MAX_POLICY_DT_S {
            return Err(format!(
                "control.physics_dt_s x control.decimation = {} s: the policy step must be at most {MAX_POLICY_DT_S} s",
                self.policy_dt_s()
            ));
        }
        for (key, v, hi) in [
            ("control.kp_nm_per_rad", self.kp_nm_per_rad, 1e6),
            ("control.kd_nm_s_per_rad", self.kd_nm_s_per_rad, 1e6),
            ("control.action_scale_rad", self.action_scale_rad, 100.0),
            ("control.clip_actions", self.clip_actions, 1e6),
        ] {
            if v > hi {
                return Err(format!("{key} must be at most {hi:e}, got {v}"));
            }
        }
        if self
            .torque_limits_nm
            .iter()
            .any(|&t| !(t.is_finite() && t > 0.0 && t <= 1e4))
        {
            return Err(format!(
                "control.torque_limits_nm must each be in (0, 1e4] N m, got {:?}",
                self.torque_limits_nm
            ));
        }
        Ok(())
    }

    /// Torque limit (N m) of joint `i` in SDK order.
    pub fn torque_limit_nm(&self, joint: usize) -> f64 {
        self.torque_limits_nm[joint % 3]
    }

    /// Joint targets (rad) for a policy action: q_default + scale * clip(action).
    pub fn joint_targets(
        &self,
        default_rad: &[f64; NUM_JOINTS],
        action: &[f32],
    ) -> [f64; NUM_JOINTS] {
        std::array::from_fn(|i| {
            let a = (action[i] as f64).clamp(-self.clip_actions, self.clip_actions);
            default_rad[i] + self.action_scale_rad * a
        })
    }

    /// tau = clip(Kp (q_target - q) - Kd qdot, +-limit)  (N m), SDK order.
    #[inline]
    pub fn pd_torques(
        &self,
        target_rad: &[f64; NUM_JOINTS],
        q_rad: &[f64; NUM_JOINTS],
        qd_rad_s: &[f64; NUM_JOINTS],
    ) -> [f64; NUM_JOINTS] {
        self.pd_torques_scaled(target_rad, q_rad, qd_rad_s, &[1.0; NUM_JOINTS])
    }

    /// [`Self::pd_torques`] of motors whose torque is `strength` times nominal
    /// (RMA's motor-strength randomisation), clipped at the same limits.
    #[inline]
    pub fn pd_torques_scaled(
        &self,
        target_rad: &[f64; NUM_JOINTS],
        q_rad: &[f64; NUM_JOINTS],
        qd_rad_s: &[f64; NUM_JOINTS],
        strength: &[f64; NUM_JOINTS],
    ) -> [f64; NUM_JOINTS] {
        std::array::from_fn(|i| {
            let tau = strength[i]
                * (self.kp_nm_per_rad * (target_rad[i] - q_rad[i])
                    - self.kd_nm_s_per_rad * qd_rad_s[i]);
            let limit = self.torque_limit_nm(i);
            tau.clamp(-limit, limit)
        })
    }
}
