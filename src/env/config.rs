//! Task configuration as data: observation, reward, risk, commands, episodes,
//! randomisation. Defaults are the RALL paper's (tables I-III) and legged_gym's.
//! Every numeric key says its accepted range; [`EnvConfig::validate`] refuses
//! anything outside it, naming the key.

use serde::{Deserialize, Serialize};

/// One scalar per observation group (legged_gym's grouping). As scales
/// (`observation.scales`) each is in [0, 1e4] (0 blanks the group); as noise
/// stds (`observation.noise_std`) each is in [0, 1e4].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObsGroups {
    pub lin_vel: f64,
    pub ang_vel: f64,
    pub gravity: f64,
    pub dof_pos: f64,
    pub dof_vel: f64,
}

/// Observation scales and noise.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ObservationConfig {
    /// Multipliers applied to each group (commands use `command_scale`, actions 1).
    pub scales: ObsGroups,
    /// Scale of (vx, vy, yaw rate) in the command slot, each in [0, 1e4].
    pub command_scale: [f64; 3],
    /// Gaussian noise std per group, in physical units (m/s, rad/s, -, rad, rad/s);
    /// added after scaling as std * scale. Commands and actions get none.
    pub noise_std: ObsGroups,
    /// Global multiplier of all noise (0 disables it), in [0, 1e4].
    pub noise_level: f64,
    /// Observations are clipped to +-clip after scaling, clip in (0, 1e6].
    pub clip: f64,
    /// The groups the env writes into each observation row, in order:
    /// "policy", "privileged", "extrinsics", "history" (`ObsGroup`).
    pub groups: Vec<super::observation::ObsGroup>,
    /// Policy observations kept in the `history` group (RMA: 50), 1..=1000.
    pub history_steps: usize,
}

impl Default for ObservationConfig {
    fn default() -> Self {
        ObservationConfig {
            scales: ObsGroups {
                lin_vel: 2.0,
                ang_vel: 0.25,
                gravity: 1.0,
                dof_pos: 1.0,
                dof_vel: 0.05,
            },
            command_scale: [2.0, 2.0, 0.25],
            noise_std: ObsGroups {
                lin_vel: 0.1,
                ang_vel: 0.2,
                gravity: 0.05,
                dof_pos: 0.01,
                dof_vel: 1.5,
            },
            noise_level: 1.0,
            clip: 100.0,
            groups: vec![super::observation::ObsGroup::Policy],
            history_steps: 50,
        }
    }
}

/// Weights of the task reward terms (paper table I); each term is multiplied by
/// its weight and by the policy dt. Every weight is in [-1e6, 1e6] (0 turns a
/// term off).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RewardConfig {
    pub lin_vel_tracking: f64,
    pub ang_vel_tracking: f64,
    pub lin_vel_z: f64,
    pub ang_vel_xy: f64,
    pub joint_acc: f64,
    pub torques: f64,
    pub action_magnitude: f64,
    pub collision: f64,
    pub action_rate: f64,
    pub torque_rate: f64,
    pub feet_air_time: f64,
    /// sigma of exp(-err^2 / sigma) ((m/s)^2 and (rad/s)^2), in [1e-9, 1e6].
    pub tracking_sigma: f64,
    /// Air time (s) that pays zero in the feet-air-time term, in [0, 1e3].
    pub feet_air_time_target_s: f64,
    /// Clip the summed task reward at 0 from below (legged_gym); risk penalties
    /// are applied after the clip so they are never hidden by it.
    pub only_positive_task_reward: bool,
}

impl RewardConfig {
    /// The term weights by key (for validation).
    pub fn weights(&self) -> [(&'static str, f64); 11] {
        [
            ("lin_vel_tracking", self.lin_vel_tracking),
            ("ang_vel_tracking", self.ang_vel_tracking),
            ("lin_vel_z", self.lin_vel_z),
            ("ang_vel_xy", self.ang_vel_xy),
            ("joint_acc", self.joint_acc),
            ("torques", self.torques),
            ("action_magnitude", self.action_magnitude),
            ("collision", self.collision),
            ("action_rate", self.action_rate),
            ("torque_rate", self.torque_rate),
            ("feet_air_time", self.feet_air_time),
        ]
    }
}

impl Default for RewardConfig {
    fn default() -> Self {
        RewardConfig {
            lin_vel_tracking: 5.0,
            ang_vel_tracking: 0.5,
            lin_vel_z: -1.0,
            ang_vel_xy: -0.05,
            joint_acc: -2.5e-7,
            torques: -2e-5,
            action_magnitude: -0.01,
            collision: -1e-3,
            action_rate: -0.01,
            torque_rate: -3e-4,
            feet_air_time: 2.0,
            tracking_sigma: 0.25,
            feet_air_time_target_s: 0.5,
            only_positive_task_reward: true,
        }
    }
}

/// One risk term: past `threshold`, `weight` is subtracted with probability p.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RiskTerm {
    /// In the term's unit (below), in [0, 1e9].
    pub threshold: f64,
    /// In [0, 1e6] (it is subtracted; 0 turns the penalty off).
    pub weight: f64,
    /// Joint terms only: one threshold per joint (SDK order) instead of `threshold`
    /// for the largest joint; the term is crossed when any joint passes its own
    /// (`rall calibrate-risk` sets them from a walking policy's gait). Each in
    /// (0, 1e9].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub per_joint: Option<[f64; crate::robot::NUM_JOINTS]>,
}

/// Risk penalties (paper table II and eq. 2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RiskConfig {
    /// Bernoulli probability that an exceeded threshold is penalised, in [0, 1].
    pub probability: f64,
    /// |pitch| (rad).
    pub base_pitch: RiskTerm,
    /// |roll| (rad).
    pub base_roll: RiskTerm,
    /// max |joint velocity| (rad/s).
    pub joint_velocity: RiskTerm,
    /// max |joint acceleration| (rad/s^2), finite difference over the policy step.
    pub joint_acceleration: RiskTerm,
    /// max |joint torque| (N m).
    pub joint_torque: RiskTerm,
}

impl Default for RiskConfig {
    fn default() -> Self {
        RiskConfig {
            probability: 1e-4,
            base_pitch: RiskTerm {
                threshold: 0.5,
                weight: 20.0,
                per_joint: None,
            },
            base_roll: RiskTerm {
                threshold: 1.0,
                weight: 100.0,
                per_joint: None,
            },
            joint_velocity: RiskTerm {
                threshold: 10.0,
                weight: 100.0,
                per_joint: None,
            },
            joint_acceleration: RiskTerm {
                threshold: 1000.0,
                weight: 100.0,
                per_joint: None,
            },
            joint_torque: RiskTerm {
                threshold: 40.0,
                weight: 150.0,
                per_joint: None,
            },
        }
    }
}

impl RiskConfig {
    /// The terms in [`super::risk::RISK_TERMS`] order, with their names.
    pub fn terms(&self) -> [(&'static str, RiskTerm); super::risk::NUM_RISK_TERMS] {
        std::array::from_fn(|i| {
            let def = &super::risk::RISK_TERMS[i];
            (def.name, (def.setting)(self))
        })
    }
}

/// Velocity command sampling (legged_gym defaults).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CommandConfig {
    /// Forward command range [lo, hi] (m/s), lo <= hi, both within +-100.
    pub vx_mps: [f64; 2],
    /// Sideways command range [lo, hi] (m/s), lo <= hi, both within +-100.
    pub vy_mps: [f64; 2],
    /// Yaw-rate command range [lo, hi] (rad/s), lo <= hi, both within +-100.
    pub yaw_rate_rad_s: [f64; 2],
    /// Seconds between command draws, in [1e-6, 1e6].
    pub resample_interval_s: f64,
    /// Planar commands with norm below this are zeroed (m/s), in [0, 1e3].
    pub zero_below_mps: f64,
}

impl Default for CommandConfig {
    fn default() -> Self {
        CommandConfig {
            vx_mps: [-1.0, 1.0],
            vy_mps: [-1.0, 1.0],
            yaw_rate_rad_s: [-1.0, 1.0],
            resample_interval_s: 10.0,
            zero_below_mps: 0.2,
        }
    }
}

/// Episode length and termination.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EpisodeConfig {
    /// Episode length (s), in [1e-6, 1e6] and at least one policy step.
    pub length_s: f64,
    /// Terminate when roll or pitch exceeds this (rad), in [1e-6, 1e3].
    pub max_tilt_rad: f64,
    /// Terminate when the trunk touches the ground.
    pub terminate_on_trunk_contact: bool,
    /// Start training with random episode progress (legged_gym), so resets spread out.
    pub randomize_initial_length: bool,
}

impl Default for EpisodeConfig {
    fn default() -> Self {
        EpisodeConfig {
            length_s: 20.0,
            max_tilt_rad: 1.2,
            terminate_on_trunk_contact: true,
            randomize_initial_length: true,
        }
    }
}

/// How pushes disturb the robot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, tag = "kind", rename_all = "snake_case")]
pub enum PushConfig {
    None,
    /// Add U[-max, max] m/s to the base x and y velocity every `interval_s` (paper table III);
    /// `interval_s` in (0, 1e6], `max_mps` in [0, 100].
    VelocityKick {
        interval_s: f64,
        max_mps: f64,
    },
    /// Apply `force_n` on the trunk along a random +-x or +-y direction every
    /// `every_steps` policy steps, held for `hold_steps` (paper's evaluation pushes);
    /// `force_n` in [0, 1e5], `every_steps` 1..=1,000,000, `hold_steps` 0..=`every_steps`.
    Force {
        force_n: f64,
        every_steps: usize,
        hold_steps: usize,
    },
}

/// Domain randomisation, sampled per episode (paper table III). Every range
/// is `[lo, hi]` with lo <= hi.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RandomizationConfig {
    /// Friction coefficient of every geom, U[lo, hi] within [0, 1e3]; `None` keeps the model's.
    pub friction: Option<[f64; 2]>,
    /// Mass added to the trunk (kg), U[lo, hi] within [-1e3, 1e3]; `None` keeps the model's.
    pub added_base_mass_kg: Option<[f64; 2]>,
    /// Torque multiplier of each motor, drawn per motor, U[lo, hi] within (0, 1e3]; `None`: 1.
    pub motor_strength: Option<[f64; 2]>,
    /// Multiplier of the PD stiffness Kp, U[lo, hi] within (0, 1e3]; `None`: 1.
    pub kp_factor: Option<[f64; 2]>,
    /// Multiplier of the PD damping Kd, U[lo, hi] within (0, 1e3]; `None`: 1.
    pub kd_factor: Option<[f64; 2]>,
    /// Offset of the trunk's centre of mass along each body axis (m), U[lo, hi]
    /// within [-0.3, 0.3]; `None`: 0.
    pub com_offset_m: Option<[f64; 2]>,
    pub push: PushConfig,
}

impl Default for RandomizationConfig {
    fn default() -> Self {
        RandomizationConfig {
            friction: Some([0.5, 1.5]),
            added_base_mass_kg: Some([-0.5, 1.0]),
            motor_strength: None,
            kp_factor: None,
            kd_factor: None,
            com_offset_m: None,
            push: PushConfig::VelocityKick {
                interval_s: 5.0,
                max_mps: 1.0,
            },
        }
    }
}

/// Everything one environment needs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EnvConfig {
    /// Robot MJCF (robot only; the scene is added from `terrain`). A relative path
    /// is looked up in the working directory, then in `$RALL_HOME`, then in the
    /// source tree `rall` was built from (see [`EnvConfig::robot_mjcf_path`]).
    pub robot_mjcf: String,
    pub control: crate::robot::ControlConfig,
    pub observation: ObservationConfig,
    pub reward: RewardConfig,
    pub risk: RiskConfig,
    pub commands: CommandConfig,
    pub episode: EpisodeConfig,
    pub randomization: RandomizationConfig,
    pub terrain: super::terrain::TerrainConfig,
}

impl Default for EnvConfig {
    fn default() -> Self {
        EnvConfig {
            robot_mjcf: "mjcf/aliengo.xml".into(),
            control: Default::default(),
            observation: Default::default(),
            reward: Default::default(),
            risk: Default::default(),
            commands: Default::default(),
            episode: Default::default(),
            randomization: Default::default(),
            terrain: Default::default(),
        }
    }
}

fn check(ok: bool, key: &str, what: impl std::fmt::Display) -> Result<(), String> {
    if ok {
        Ok(())
    } else {
        Err(format!("{key}: {what}"))
    }
}

/// Largest observation scale a config may set.
const MAX_SCALE: f64 = 1e4;
/// Largest reward weight (in magnitude) a config may set.
const MAX_WEIGHT: f64 = 1e6;
/// Largest risk threshold a config may set (any unit).
const MAX_THRESHOLD: f64 = 1e9;
/// Largest command or push speed a config may set (m/s, rad/s).
const MAX_COMMAND: f64 = 100.0;

/// `v` finite and in `[lo, hi]`.
fn check_within(key: &str, v: f64, lo: f64, hi: f64) -> Result<(), String> {
    check(
        v.is_finite() && (lo..=hi).contains(&v),
        key,
        format!("must be a finite number in [{lo:e}, {hi:e}], got {v}"),
    )
}

/// `r` = [lo, hi], finite, lo <= hi, both within `[min, max]`.
fn check_range_within(r: [f64; 2], key: &str, min: f64, max: f64) -> Result<(), String> {
    check(
        r[0].is_finite() && r[1].is_finite() && r[0] <= r[1] && r[0] >= min && r[1] <= max,
        key,
        format!("must be [lo, hi] with lo <= hi within [{min}, {max}], got {r:?}"),
    )
}

impl EnvConfig {
    /// Where [`EnvConfig::robot_mjcf`] is: as given when it exists (absolute, or
    /// relative to the working directory), else under `$RALL_HOME`, else under the
    /// source tree of this build, so `rall` runs from any directory. `None` when
    /// none of these exists.
    pub fn robot_mjcf_path(&self) -> Option<std::path::PathBuf> {
        resolve_data_path(&self.robot_mjcf)
    }

    /// The robot MJCF's text and the file it came from, found as
    /// [`EnvConfig::robot_mjcf_path`] says; else the path tried and why it failed
    /// (naming every place looked in when the file was found nowhere).
    pub fn read_robot_mjcf(
        &self,
    ) -> Result<(std::path::PathBuf, String), (std::path::PathBuf, String)> {
        let found = self.robot_mjcf_path();
        let path = found
            .clone()
            .unwrap_or_else(|| self.robot_mjcf.clone().into());
        match std::fs::read_to_string(&path) {
            Ok(text) => Ok((path, text)),
            Err(e) if found.is_none() => Err((
                path,
                format!(
                    "{e}; looked in the working directory, in $RALL_HOME and in {}",
                    env!("CARGO_MANIFEST_DIR")
                ),
            )),
            Err(e) => Err((path, e.to_string())),
        }
    }

    /// Refuses impossible values with a message naming the key.
    pub fn validate(&self) -> Result<(), String> {
        self.control.validate()?;
        self.validate_noise()?;
        self.validate_magnitudes()?;
        self.validate_groups()?;
        check(
            self.reward.tracking_sigma > 0.0,
            "reward.tracking_sigma",
            "must be positive",
        )?;
        self.validate_risk()?;
        self.validate_commands_and_episode()?;
        self.validate_randomization()?;
        self.validate_push()?;
        self.terrain.validate()?;
        Ok(())
    }

    /// Observation noise: every std finite and >= 0.
    fn validate_noise(&self) -> Result<(), String> {
        let o = &self.observation;
        for (k, v) in [
            ("observation.noise_std.lin_vel", o.noise_std.lin_vel),
            ("observation.noise_std.ang_vel", o.noise_std.ang_vel),
            ("observation.noise_std.gravity", o.noise_std.gravity),
            ("observation.noise_std.dof_pos", o.noise_std.dof_pos),
            ("observation.noise_std.dof_vel", o.noise_std.dof_vel),
            ("observation.noise_level", o.noise_level),
        ] {
            check_within(k, v, 0.0, MAX_SCALE)?;
        }
        Ok(())
    }

    /// Observation groups: `policy` among them, none twice; a sane history length.
    fn validate_groups(&self) -> Result<(), String> {
        let o = &self.observation;
        check(
            o.groups.contains(&super::observation::ObsGroup::Policy),
            "observation.groups",
            format!("must include \"policy\", got {:?}", o.groups),
        )?;
        for (i, g) in o.groups.iter().enumerate() {
            check(
                !o.groups[..i].contains(g),
                "observation.groups",
                format!("lists {:?} twice", g.name()),
            )?;
        }
        check(
            (1..=1000).contains(&o.history_steps),
            "observation.history_steps",
            format!("must be in 1..=1000, got {}", o.history_steps),
        )?;
        Ok(())
    }

    /// Risk: a probability, and each term's threshold and weight.
    fn validate_risk(&self) -> Result<(), String> {
        let p = self.risk.probability;
        check(
            (0.0..=1.0).contains(&p),
            "risk.probability",
            format!("must be in [0, 1], got {p}"),
        )?;
        for (i, (name, t)) in self.risk.terms().into_iter().enumerate() {
            check_within(
                &format!("risk.{name}.threshold"),
                t.threshold,
                0.0,
                MAX_THRESHOLD,
            )?;
            if let Some(per) = t.per_joint {
                check(
                    super::risk::RISK_TERMS[i].per_joint.is_some(),
                    &format!("risk.{name}.per_joint"),
                    "applies to the joint terms only (joint_velocity, joint_acceleration, joint_torque)",
                )?;
                check(
                    per.iter()
                        .all(|v| v.is_finite() && *v > 0.0 && *v <= MAX_THRESHOLD),
                    &format!("risk.{name}.per_joint"),
                    "every joint's threshold must be in (0, 1e9]",
                )?;
            }
            check(
                t.weight.is_finite() && (0.0..=MAX_WEIGHT).contains(&t.weight),
                &format!("risk.{name}.weight"),
                format!("must be in [0, 1e6] (it is subtracted), got {}", t.weight),
            )?;
        }
        Ok(())
    }

    /// Command ranges and intervals, episode length and tilt limit.
    fn validate_commands_and_episode(&self) -> Result<(), String> {
        let c = &self.commands;
        for (key, r) in [
            ("commands.vx_mps", c.vx_mps),
            ("commands.vy_mps", c.vy_mps),
            ("commands.yaw_rate_rad_s", c.yaw_rate_rad_s),
        ] {
            check_range_within(r, key, -MAX_COMMAND, MAX_COMMAND)?;
        }
        check(
            c.resample_interval_s > 0.0,
            "commands.resample_interval_s",
            "must be positive",
        )?;
        check(
            self.episode.length_s > 0.0,
            "episode.length_s",
            "must be positive",
        )?;
        check(
            self.episode.max_tilt_rad > 0.0,
            "episode.max_tilt_rad",
            "must be positive",
        )?;
        let policy_dt = self.control.policy_dt_s();
        check(
            self.episode.length_s >= policy_dt,
            "episode.length_s",
            format!(
                "must hold at least one policy step ({policy_dt} s), got {}",
                self.episode.length_s
            ),
        )?;
        Ok(())
    }

    /// Domain-randomisation ranges (friction, mass, motors, gains, centre of mass).
    fn validate_randomization(&self) -> Result<(), String> {
        let r = &self.randomization;
        if let Some(f) = r.friction {
            check_range_within(f, "randomization.friction", 0.0, 1e3)?;
        }
        if let Some(m) = r.added_base_mass_kg {
            check_range_within(m, "randomization.added_base_mass_kg", -1e3, 1e3)?;
        }
        for (key, range) in [
            ("randomization.motor_strength", r.motor_strength),
            ("randomization.kp_factor", r.kp_factor),
            ("randomization.kd_factor", r.kd_factor),
        ] {
            if let Some(f) = range {
                check_range_within(f, key, 0.0, 1e3)?;
                check(f[0] > 0.0, key, format!("must be > 0, got {f:?}"))?;
            }
        }
        if let Some(c) = r.com_offset_m {
            check_range_within(c, "randomization.com_offset_m", -0.3, 0.3)?;
        }
        Ok(())
    }

    /// Pushes: positive intervals, non-negative strengths.
    fn validate_push(&self) -> Result<(), String> {
        let r = &self.randomization;
        match r.push {
            PushConfig::None => {}
            PushConfig::VelocityKick {
                interval_s,
                max_mps,
            } => {
                check(
                    interval_s > 0.0 && interval_s <= 1e6,
                    "randomization.push.interval_s",
                    format!("must be in (0, 1e6], got {interval_s}"),
                )?;
                check_within("randomization.push.max_mps", max_mps, 0.0, MAX_COMMAND)?;
            }
            PushConfig::Force {
                force_n,
                every_steps,
                hold_steps,
            } => {
                check_within("randomization.push.force_n", force_n, 0.0, 1e5)?;
                check(
                    (1..=1_000_000).contains(&every_steps),
                    "randomization.push.every_steps",
                    format!("must be in 1..=1000000, got {every_steps}"),
                )?;
                check(
                    hold_steps <= every_steps,
                    "randomization.push.hold_steps",
                    "must be <= every_steps",
                )?;
            }
        }
        Ok(())
    }

    /// Every scale, weight and duration finite and within a sane magnitude
    /// (a scale of 1e30 or a clip of inf would train on garbage).
    fn validate_magnitudes(&self) -> Result<(), String> {
        let o = &self.observation;
        let s = &o.scales;
        let scales = [
            ("observation.scales.lin_vel", s.lin_vel),
            ("observation.scales.ang_vel", s.ang_vel),
            ("observation.scales.gravity", s.gravity),
            ("observation.scales.dof_pos", s.dof_pos),
            ("observation.scales.dof_vel", s.dof_vel),
            ("observation.command_scale[0]", o.command_scale[0]),
            ("observation.command_scale[1]", o.command_scale[1]),
            ("observation.command_scale[2]", o.command_scale[2]),
            ("observation.noise_level", o.noise_level),
        ];
        for (key, v) in scales {
            check_within(key, v, 0.0, MAX_SCALE)?;
        }
        check(
            o.clip.is_finite() && o.clip > 0.0 && o.clip <= 1e6,
            "observation.clip",
            format!("must be a finite number in (0, 1e6], got {}", o.clip),
        )?;
        let r = &self.reward;
        for (key, v) in r.weights() {
            check_within(&format!("reward.{key}"), v, -MAX_WEIGHT, MAX_WEIGHT)?;
        }
        check_within("reward.tracking_sigma", r.tracking_sigma, 1e-9, 1e6)?;
        check_within(
            "reward.feet_air_time_target_s",
            r.feet_air_time_target_s,
            0.0,
            1e3,
        )?;
        let c = &self.commands;
        check_within("commands.zero_below_mps", c.zero_below_mps, 0.0, 1e3)?;
        check_within(
            "commands.resample_interval_s",
            c.resample_interval_s,
            1e-6,
            1e6,
        )?;
        check_within("episode.length_s", self.episode.length_s, 1e-6, 1e6)?;
        check_within("episode.max_tilt_rad", self.episode.max_tilt_rad, 1e-6, 1e3)?;
        Ok(())
    }

    /// Values in one observation row (all configured groups).
    pub fn obs_width(&self) -> usize {
        self.obs_layout().width()
    }

    /// The observation row's groups and widths.
    pub fn obs_layout(&self) -> crate::learn::ObsLayout {
        super::observation::obs_layout(&self.observation)
    }

    /// Policy steps per episode.
    pub fn max_episode_steps(&self) -> usize {
        (self.episode.length_s / self.control.policy_dt_s()).round() as usize
    }
}

/// A data file of the repository (`mjcf/...`) found from any working directory: the
/// path as given, else under `$RALL_HOME`, else under the source tree of this build.
pub fn resolve_data_path(path: &str) -> Option<std::path::PathBuf> {
    let p = std::path::Path::new(path);
    if p.exists() {
        return Some(p.to_path_buf());
    }
    if p.is_absolute() {
        return None;
    }
    let homes = [
        std::env::var_os("RALL_HOME").map(std::path::PathBuf::from),
        Some(std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"))),
    ];
    homes
        .into_iter()
        .flatten()
        .map(|h| h.join(p))
        .find(|c| c.exists())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn repository_files_are_found_from_any_working_directory() {
        // Relative to the working directory or not, the default robot is found: the
        // source tree of this build is the last place looked in.
        let found = EnvConfig::default().robot_mjcf_path().expect("found");
        assert!(found.ends_with("mjcf/aliengo.xml") && found.exists());
        assert!(resolve_data_path("mjcf/no-such-robot.xml").is_none());
        assert!(resolve_data_path("/no/such/dir/aliengo.xml").is_none());
        let abs = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("mjcf/aliengo.xml");
        assert_eq!(resolve_data_path(abs.to_str().unwrap()), Some(abs));
    }

    #[test]
    fn a_missing_robot_file_says_where_it_was_looked_for() {
        let cfg = EnvConfig {
            robot_mjcf: "mjcf/no-such-robot.xml".into(),
            ..EnvConfig::default()
        };
        let err = match crate::env::build_scene(&cfg, 0) {
            Ok(_) => panic!("a missing robot file built a scene"),
            Err(e) => format!("{e:#}"),
        };
        assert!(err.contains("mjcf/no-such-robot.xml"), "{err}");
        assert!(err.contains("RALL_HOME"), "{err}");
    }
}
