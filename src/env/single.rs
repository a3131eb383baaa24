//! [`Env`]: one robot. `reset` and `step(action)` over plain state; commands,
//! randomisation and pushes are data sampled from the env's own RNG.

use std::sync::Arc;
use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::config::{EnvConfig, PushConfig};
use super::observation::{write_observation, ObsGroup, ACT_DIM, OBS_DIM};
use super::privileged::PrivilegedState;
use super::reward::{reward_terms, RewardInputs, NUM_REWARD_TERMS};
use super::risk::{evaluate_risk, RiskOutcome, NUM_RISK_TERMS};
use super::snapshot::{StateReader, StateWriter};
use super::state::{roll_pitch_yaw, rotate_inverse, RobotState};
use super::terrain::Terrain;
use crate::robot::{Part, Robot, NUM_JOINTS};
use crate::sim::{ArenaUse, Model, Result};

/// Domain randomisation drawn at the start of an episode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EpisodeDraw {
    /// Friction coefficient given to every geom (`None`: the model's own).
    pub friction: Option<f64>,
    /// Mass added to the trunk (kg).
    pub added_base_mass_kg: f64,
    /// Torque multiplier of each motor, SDK order.
    pub motor_strength: [f64; NUM_JOINTS],
    /// Multipliers of the PD gains.
    pub kp_factor: f64,
    pub kd_factor: f64,
    /// Trunk centre-of-mass offset in the body frame (m).
    pub com_offset_m: [f64; 3],
}

impl Default for EpisodeDraw {
    fn default() -> Self {
        EpisodeDraw {
            friction: None,
            added_base_mass_kg: 0.0,
            motor_strength: [1.0; NUM_JOINTS],
            kp_factor: 1.0,
            kd_factor: 1.0,
            com_offset_m: [0.0; 3],
        }
    }
}

/// Why an episode ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum EpisodeEnd {
    TimeOut,
    TrunkContact,
    Tilt,
    /// MuJoCo flagged a bad state (NaN, divergence); the env was reset.
    Unstable,
}

/// Risk firings this close before a fall count as marking danger (s).
pub const FALL_WINDOW_S: f64 = 1.0;

/// Summary of a finished episode, for logging and the curriculum.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EpisodeSummary {
    pub env_index: usize,
    pub steps: usize,
    pub end: EpisodeEnd,
    /// Sum over the episode of each weighted task reward term.
    pub reward_terms: [f64; NUM_REWARD_TERMS],
    /// Sum of the risk penalties subtracted.
    pub risk_penalty: f64,
    pub total_reward: f64,
    pub risk_exceeded: [u32; NUM_RISK_TERMS],
    pub risk_fired: [u32; NUM_RISK_TERMS],
    /// Of `risk_fired`, the firings within [`FALL_WINDOW_S`] before the episode
    /// ended in a fall (0 for a time-out): the penalties that marked danger.
    pub risk_fired_before_fall: [u32; NUM_RISK_TERMS],
    /// Terrain level the episode ran on.
    pub terrain_level: usize,
    /// Horizontal distance from the spawn point (m).
    pub distance_m: f64,
    /// Integral of the commanded planar speed over the episode (m).
    pub commanded_distance_m: f64,
}

/// What one policy step produced.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepResult {
    pub reward: f64,
    /// The episode ended (termination or time-out). `obs` then holds the final
    /// observation too; call [`Env::reset`] before stepping again (VecEnv does).
    pub done: bool,
    /// The episode ended by time-out (the learner bootstraps from `final_obs`).
    pub time_out: bool,
    pub risk: RiskOutcome,
    /// A push started this step.
    pub pushed: bool,
}

/// An active force push (the evaluation scenario's 100 N pushes).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ForcePush {
    /// World-frame force on the trunk (N).
    pub force_n: [f64; 3],
    pub steps_left: usize,
}

pub struct Env {
    pub index: usize,
    cfg: Arc<EnvConfig>,
    robot: Robot,
    terrain: Option<Arc<Terrain>>,
    rng: ChaCha8Rng,
    /// Friction of every geom in the unrandomised model.
    base_friction: Vec<[f64; 3]>,
    /// Body and subtree masses in the unrandomised model (kg).
    base_body_mass_kg: Vec<f64>,
    base_subtree_mass_kg: Vec<f64>,
    /// Trunk centre of mass in the unrandomised model (m, body frame).
    base_trunk_ipos_m: [f64; 3],
    /// The trunk and its ancestors: the subtrees that carry added trunk mass.
    trunk_chain: Vec<usize>,
    max_steps: usize,
    // --- episode state ---
    pub draw: EpisodeDraw,
    command: [f64; 3],
    action: [f32; ACT_DIM],
    previous_action: [f32; ACT_DIM],
    previous_torques_nm: [f64; NUM_JOINTS],
    state: RobotState,
    feet_air_time_s: [f64; 4],
    step_in_episode: usize,
    spawn_xy_m: [f64; 2],
    pub terrain_level: usize,
    pub terrain_type: usize,
    force_push: ForcePush,
    /// The push of the current step, for the privileged group.
    push_force_now_n: [f64; 3],
    kick_now_mps: [f64; 2],
    /// This step's policy observation and (newest first) the `history` group.
    policy_obs: [f32; OBS_DIM],
    history: Vec<f32>,
    commanded_distance_m: f64,
    sums: EpisodeSummary,
    /// (risk term, step in episode) of the firings of the last [`FALL_WINDOW_S`].
    recent_firings: Vec<(usize, usize)>,
    /// Physics failures since creation.
    pub instabilities: u64,
    /// The most of MuJoCo's arena used in any finished episode.
    arena_peak: ArenaUse,
    last_summary: Option<EpisodeSummary>,
    /// What the last `step` returned (read by `VecEnv` for batch counters).
    pub last_step: StepResult,
    /// CPU time of `step` since `VecEnv` last read it: in the physics (PD +
    /// `mj_step` x decimation) and in total (physics + observation, reward,
    /// risk, pushes), nanoseconds.
    pub physics_ns: u64,
    pub step_ns: u64,
}

impl Env {
    /// Builds env `index` over `base_model`, shared with other envs (one
    /// model for all, the terrain stored once): its randomisation lives in its
    /// robot's parameters, written into the stepping thread's working copy of
    /// the model before each step, so it never leaks between envs. `seed` and
    /// `index` fix its random stream.
    pub fn new(
        cfg: Arc<EnvConfig>,
        base_model: &Arc<Model>,
        terrain: Option<Arc<Terrain>>,
        seed: u64,
        index: usize,
    ) -> Result<Env> {
        let robot = Robot::shared(base_model.clone(), cfg.control.clone())?;
        Env::with_robot(cfg, robot, terrain, seed, index)
    }

    /// As [`Env::new`], with a model copy of the env's own (more memory, same
    /// physics: the reference the shared model is checked against).
    pub fn with_own_model(
        cfg: Arc<EnvConfig>,
        base_model: &Model,
        terrain: Option<Arc<Terrain>>,
        seed: u64,
        index: usize,
    ) -> Result<Env> {
        let robot = Robot::new(base_model.try_clone()?, cfg.control.clone())?;
        Env::with_robot(cfg, robot, terrain, seed, index)
    }

    fn with_robot(
        cfg: Arc<EnvConfig>,
        robot: Robot,
        terrain: Option<Arc<Terrain>>,
        seed: u64,
        index: usize,
    ) -> Result<Env> {
        let base = robot.params();
        let base_friction = base.geom_friction().to_vec();
        let base_body_mass_kg = base.body_mass_kg().to_vec();
        let base_subtree_mass_kg = base.body_subtree_mass_kg().to_vec();
        let base_trunk_ipos_m = base.body_ipos_m()[robot.layout.trunk_body];
        let o = &cfg.observation;
        let history_len = if o.groups.contains(&ObsGroup::History) {
            o.history_steps * OBS_DIM
        } else {
            0
        };
        let mut trunk_chain = vec![robot.layout.trunk_body];
        while let Some(&b) = trunk_chain.last().filter(|&&b| b != 0) {
            trunk_chain.push(robot.model().body_parent(b));
        }
        let max_steps = cfg.max_episode_steps();
        let rng =
            ChaCha8Rng::seed_from_u64(seed ^ (index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let env = Env {
            index,
            cfg,
            robot,
            terrain,
            rng,
            base_friction,
            base_body_mass_kg,
            base_subtree_mass_kg,
            base_trunk_ipos_m,
            trunk_chain,
            max_steps,
            draw: EpisodeDraw::default(),
            command: [0.0; 3],
            action: [0.0; ACT_DIM],
            previous_action: [0.0; ACT_DIM],
            previous_torques_nm: [0.0; NUM_JOINTS],
            state: RobotState::default(),
            feet_air_time_s: [0.0; 4],
            step_in_episode: 0,
            spawn_xy_m: [0.0; 2],
            terrain_level: 0,
            terrain_type: 0,
            force_push: ForcePush::default(),
            push_force_now_n: [0.0; 3],
            kick_now_mps: [0.0; 2],
            policy_obs: [0.0; OBS_DIM],
            history: vec![0.0; history_len],
            commanded_distance_m: 0.0,
            sums: empty_summary(index),
            recent_firings: Vec::new(),
            instabilities: 0,
            arena_peak: ArenaUse::default(),
            last_summary: None,
            last_step: StepResult::default(),
            physics_ns: 0,
            step_ns: 0,
        };
        Ok(env)
    }

    /// The most of MuJoCo's arena (contacts, constraint rows, stack) this env
    /// has used in any episode so far, beside the capacity.
    pub fn arena_use(&self) -> ArenaUse {
        self.arena_peak.max(self.robot.data().arena_use())
    }

    /// The summary of the episode that ended in the last `step`, once.
    pub fn take_summary(&mut self) -> Option<EpisodeSummary> {
        self.last_summary.take()
    }

    /// Values per observation row (all configured groups).
    pub fn obs_width(&self) -> usize {
        self.cfg.obs_width()
    }
    pub fn config(&self) -> &EnvConfig {
        &self.cfg
    }
    pub fn robot(&self) -> &Robot {
        &self.robot
    }
    /// Mutable access for scenarios (payload joints, external forces).
    pub fn robot_mut(&mut self) -> &mut Robot {
        &mut self.robot
    }
    pub fn command(&self) -> [f64; 3] {
        self.command
    }
    /// Overrides the command (eval scenarios, the viewer).
    pub fn set_command(&mut self, command: [f64; 3]) {
        self.command = command;
    }
    pub fn state(&self) -> &RobotState {
        &self.state
    }
    pub fn step_in_episode(&self) -> usize {
        self.step_in_episode
    }
    pub fn max_steps(&self) -> usize {
        self.max_steps
    }
    pub fn force_push(&self) -> ForcePush {
        self.force_push
    }
    /// Sets the step counter (legged_gym spreads initial resets this way).
    pub fn set_step_in_episode(&mut self, step: usize) {
        self.step_in_episode = step.min(self.max_steps.saturating_sub(1));
    }
    /// A uniform random episode progress for the first episode of training.
    pub fn randomize_episode_progress(&mut self) {
        let s = self.rng.gen_range(0..self.max_steps);
        self.set_step_in_episode(s);
    }

    /// Starts a new episode and writes its first observation.
    pub fn reset(&mut self, obs: &mut [f32]) -> Result<()> {
        self.arena_peak = self.arena_peak.max(self.robot.data().arena_use());
        self.apply_randomization();
        self.robot.reset_to_default()?;
        self.place_at_spawn()?;
        self.command = self.sample_command();
        self.action = [0.0; ACT_DIM];
        self.previous_action = [0.0; ACT_DIM];
        self.previous_torques_nm = [0.0; NUM_JOINTS];
        self.feet_air_time_s = [0.0; 4];
        self.step_in_episode = 0;
        self.force_push = ForcePush::default();
        self.push_force_now_n = [0.0; 3];
        self.kick_now_mps = [0.0; 2];
        self.history.fill(0.0);
        self.commanded_distance_m = 0.0;
        self.sums = empty_summary(self.index);
        self.sums.terrain_level = self.terrain_level;
        self.recent_firings.clear();
        let qd = self.robot.layout.joint_vel(self.robot.data().qvel());
        self.state = self.measure(&qd, &[0.0; NUM_JOINTS]);
        self.observe(obs);
        Ok(())
    }

    /// Draws this episode's friction and base mass and writes them into the
    /// robot's parameters (absolute values from the unrandomised model, so the
    /// result does not depend on earlier episodes).
    fn apply_randomization(&mut self) {
        let r = &self.cfg.randomization;
        let friction = r.friction.map(|[lo, hi]| self.rng.gen_range(lo..=hi));
        let added = r
            .added_base_mass_kg
            .map_or(0.0, |[lo, hi]| self.rng.gen_range(lo..=hi));
        // drawn only when configured, so that configs without them keep their random stream
        let motor_strength = match r.motor_strength {
            Some([lo, hi]) => std::array::from_fn(|_| self.rng.gen_range(lo..=hi)),
            None => [1.0; NUM_JOINTS],
        };
        let kp_factor = r
            .kp_factor
            .map_or(1.0, |[lo, hi]| self.rng.gen_range(lo..=hi));
        let kd_factor = r
            .kd_factor
            .map_or(1.0, |[lo, hi]| self.rng.gen_range(lo..=hi));
        let com_offset_m = match r.com_offset_m {
            Some([lo, hi]) => std::array::from_fn(|_| self.rng.gen_range(lo..=hi)),
            None => [0.0; 3],
        };
        self.apply_draw(EpisodeDraw {
            friction,
            added_base_mass_kg: added,
            motor_strength,
            kp_factor,
            kd_factor,
            com_offset_m,
        });
    }

    /// Writes `draw` into the robot's parameters and gains.
    fn apply_draw(&mut self, draw: EpisodeDraw) {
        let EpisodeDraw {
            friction,
            added_base_mass_kg: added,
            motor_strength,
            kp_factor,
            kd_factor,
            com_offset_m,
        } = draw;
        self.draw = draw;
        self.robot.motor_strength = motor_strength;
        self.robot.control.kp_nm_per_rad = self.cfg.control.kp_nm_per_rad * kp_factor;
        self.robot.control.kd_nm_s_per_rad = self.cfg.control.kd_nm_s_per_rad * kd_factor;
        let trunk = self.robot.layout.trunk_body;
        let params = self.robot.params_mut();
        for (g, base) in params
            .geom_friction_mut()
            .iter_mut()
            .zip(&self.base_friction)
        {
            *g = [friction.unwrap_or(base[0]), base[1], base[2]];
        }
        params
            .body_mass_kg_mut()
            .copy_from_slice(&self.base_body_mass_kg);
        params.body_mass_kg_mut()[trunk] += added;
        let subtree = params.body_subtree_mass_kg_mut();
        subtree.copy_from_slice(&self.base_subtree_mass_kg);
        for &b in &self.trunk_chain {
            subtree[b] += added;
        }
        let ipos = &mut params.body_ipos_m_mut()[trunk];
        for (axis, p) in ipos.iter_mut().enumerate() {
            *p = self.base_trunk_ipos_m[axis] + com_offset_m[axis];
        }
    }

    /// Puts the env on terrain tile (level, type) for its next episode.
    pub fn set_terrain_cell(&mut self, level: usize, terrain_type: usize) {
        self.terrain_level = level;
        self.terrain_type = terrain_type;
    }

    /// Moves the robot to its spawn point (terrain tile centre or the origin).
    fn place_at_spawn(&mut self) -> Result<()> {
        let origin = match &self.terrain {
            Some(t) => t.tile_origin(self.terrain_level, self.terrain_type),
            None => [0.0, 0.0, 0.0],
        };
        let a = self.robot.layout.root_qpos_adr;
        let qpos = self.robot.data_mut().qpos_mut();
        qpos[a] += origin[0];
        qpos[a + 1] += origin[1];
        qpos[a + 2] += origin[2];
        self.spawn_xy_m = [qpos[a], qpos[a + 1]];
        self.robot.forward()
    }

    fn sample_command(&mut self) -> [f64; 3] {
        let c = &self.cfg.commands;
        let mut cmd = [
            self.rng.gen_range(c.vx_mps[0]..=c.vx_mps[1]),
            self.rng.gen_range(c.vy_mps[0]..=c.vy_mps[1]),
            self.rng
                .gen_range(c.yaw_rate_rad_s[0]..=c.yaw_rate_rad_s[1]),
        ];
        if (cmd[0] * cmd[0] + cmd[1] * cmd[1]).sqrt() < c.zero_below_mps {
            cmd[0] = 0.0;
            cmd[1] = 0.0;
        }
        cmd
    }

    /// One policy step. On an episode end `final_obs` (and `obs`) hold the last
    /// observation of the finished episode and the caller must [`Env::reset`].
    /// Physics failures end the episode (counted), never panic.
    pub fn step(&mut self, action: &[f32], obs: &mut [f32], final_obs: &mut [f32]) -> StepResult {
        let start = Instant::now();
        let result = self.step_untimed(action, obs, final_obs);
        self.step_ns += start.elapsed().as_nanos() as u64;
        result
    }

    fn step_untimed(
        &mut self,
        action: &[f32],
        obs: &mut [f32],
        final_obs: &mut [f32],
    ) -> StepResult {
        debug_assert_eq!(action.len(), ACT_DIM);
        self.previous_action = self.action;
        self.action.copy_from_slice(action);
        let pushed = self.apply_pushes();
        let qd_before = self.robot.layout.joint_vel(self.robot.data().qvel());
        let mut result = StepResult {
            pushed,
            ..Default::default()
        };
        let physics_start = Instant::now();
        let torques = self.robot.policy_step(&self.action);
        self.physics_ns += physics_start.elapsed().as_nanos() as u64;
        let torques = match torques {
            Ok(t) => t,
            Err(_) => {
                self.instabilities += 1;
                return self.finish(EpisodeEnd::Unstable, result, obs, final_obs);
            }
        };
        self.step_in_episode += 1;
        self.state = self.measure(&qd_before, &torques);
        let dt = self.cfg.control.policy_dt_s();
        self.commanded_distance_m += self.command[0].hypot(self.command[1]) * dt;
        let touchdown = self.update_feet_air_time(dt);
        let terms = reward_terms(
            &RewardInputs {
                state: &self.state,
                previous_torques_nm: &self.previous_torques_nm,
                action: &self.action,
                previous_action: &self.previous_action,
                command: &self.command,
                touchdown_air_time_s: &touchdown,
            },
            &self.cfg.reward,
            dt,
        );
        self.previous_torques_nm = torques;
        let mut task = terms.sum();
        if self.cfg.reward.only_positive_task_reward {
            task = task.max(0.0);
        }
        let risk = evaluate_risk(&self.state, &self.cfg.risk, &mut self.rng);
        result.risk = risk;
        result.reward = task - risk.penalty;
        self.accumulate(&terms.0, &risk, result.reward);
        self.maybe_resample_command();
        if let Some(end) = self.termination() {
            return self.finish(end, result, obs, final_obs);
        }
        self.observe(obs);
        result
    }

    fn accumulate(&mut self, terms: &[f64; NUM_REWARD_TERMS], risk: &RiskOutcome, reward: f64) {
        for (s, t) in self.sums.reward_terms.iter_mut().zip(terms) {
            *s += t;
        }
        for i in 0..NUM_RISK_TERMS {
            self.sums.risk_exceeded[i] += risk.exceeded[i] as u32;
            self.sums.risk_fired[i] += risk.fired[i] as u32;
            if risk.fired[i] {
                self.recent_firings.push((i, self.step_in_episode));
            }
        }
        let window = self.fall_window_steps();
        let now = self.step_in_episode;
        self.recent_firings.retain(|&(_, s)| s + window > now);
        self.sums.risk_penalty += risk.penalty;
        self.sums.total_reward += reward;
    }

    /// [`FALL_WINDOW_S`] in policy steps.
    fn fall_window_steps(&self) -> usize {
        (FALL_WINDOW_S / self.cfg.control.policy_dt_s())
            .round()
            .max(1.0) as usize
    }

    fn termination(&self) -> Option<EpisodeEnd> {
        let e = &self.cfg.episode;
        if e.terminate_on_trunk_contact && self.state.trunk_on_ground {
            Some(EpisodeEnd::TrunkContact)
        } else if self.state.roll_rad.abs() > e.max_tilt_rad
            || self.state.pitch_rad.abs() > e.max_tilt_rad
        {
            Some(EpisodeEnd::Tilt)
        } else if self.step_in_episode >= self.max_steps {
            Some(EpisodeEnd::TimeOut)
        } else {
            None
        }
    }

    /// Ends the episode: records the summary and the true final observation.
    /// The caller resets (VecEnv does, after updating the curriculum).
    fn finish(
        &mut self,
        end: EpisodeEnd,
        mut result: StepResult,
        obs: &mut [f32],
        final_obs: &mut [f32],
    ) -> StepResult {
        result.done = true;
        result.time_out = end == EpisodeEnd::TimeOut;
        if end == EpisodeEnd::Unstable {
            final_obs.fill(0.0);
        } else {
            self.observe(final_obs);
        }
        let pos = self.robot.base_pos_m();
        let distance =
            ((pos[0] - self.spawn_xy_m[0]).powi(2) + (pos[1] - self.spawn_xy_m[1]).powi(2)).sqrt();
        self.sums.steps = self.step_in_episode;
        self.sums.end = end;
        self.sums.distance_m = if distance.is_finite() { distance } else { 0.0 };
        self.sums.commanded_distance_m = self.commanded_distance_m;
        if end != EpisodeEnd::TimeOut {
            for &(term, _) in &self.recent_firings {
                self.sums.risk_fired_before_fall[term] += 1;
            }
        }
        self.last_summary = Some(self.sums);
        obs.copy_from_slice(final_obs);
        result
    }

    fn apply_pushes(&mut self) -> bool {
        let trunk = self.robot.layout.trunk_body;
        self.kick_now_mps = [0.0; 2];
        self.push_force_now_n = [0.0; 3];
        match self.cfg.randomization.push {
            PushConfig::None => false,
            PushConfig::VelocityKick {
                interval_s,
                max_mps,
            } => {
                let every = (interval_s / self.cfg.control.policy_dt_s())
                    .round()
                    .max(1.0) as usize;
                if self.step_in_episode > 0 && self.step_in_episode.is_multiple_of(every) {
                    self.kick_now_mps = self.random_kick(max_mps);
                    true
                } else {
                    false
                }
            }
            PushConfig::Force {
                force_n,
                every_steps,
                hold_steps,
            } => {
                let start =
                    self.step_in_episode > 0 && self.step_in_episode.is_multiple_of(every_steps);
                if start {
                    let dir = self.rng.gen_range(0..4);
                    let f = [
                        [force_n, 0.0],
                        [-force_n, 0.0],
                        [0.0, force_n],
                        [0.0, -force_n],
                    ][dir];
                    self.force_push = ForcePush {
                        force_n: [f[0], f[1], 0.0],
                        steps_left: hold_steps,
                    };
                }
                let frc = &mut self.robot.data_mut().xfrc_applied_mut()[trunk];
                if self.force_push.steps_left > 0 {
                    frc[..3].copy_from_slice(&self.force_push.force_n);
                    self.force_push.steps_left -= 1;
                    self.push_force_now_n = self.force_push.force_n;
                } else {
                    frc[..3].fill(0.0);
                }
                start
            }
        }
    }

    /// A push as in paper table III: adds U[-max, max] m/s to the base x and y
    /// velocity; returns the change applied.
    pub fn random_kick(&mut self, max_mps: f64) -> [f64; 2] {
        let dv = [
            self.rng.gen_range(-max_mps..=max_mps),
            self.rng.gen_range(-max_mps..=max_mps),
        ];
        self.kick_base_velocity(dv);
        dv
    }

    /// Adds `dv` (m/s, world x and y) to the base velocity.
    pub fn kick_base_velocity(&mut self, dv_mps: [f64; 2]) {
        let a = self.robot.layout.root_dof_adr;
        let qvel = self.robot.data_mut().qvel_mut();
        qvel[a] += dv_mps[0];
        qvel[a + 1] += dv_mps[1];
    }

    fn maybe_resample_command(&mut self) {
        let every = (self.cfg.commands.resample_interval_s / self.cfg.control.policy_dt_s())
            .round()
            .max(1.0) as usize;
        if self.step_in_episode.is_multiple_of(every) {
            self.command = self.sample_command();
        }
    }

    /// Air time bookkeeping; returns each foot's air time at touchdown (0 if none).
    fn update_feet_air_time(&mut self, dt: f64) -> [f64; 4] {
        let mut touchdown = [0.0; 4];
        let feet = self
            .feet_air_time_s
            .iter_mut()
            .zip(&self.state.foot_contact);
        for (leg, (air_s, &contact)) in feet.enumerate() {
            *air_s += dt;
            if contact {
                if *air_s > dt {
                    touchdown[leg] = *air_s;
                }
                *air_s = 0.0;
            }
        }
        touchdown
    }

    /// The plain state snapshot after a policy step.
    fn measure(&self, qd_before: &[f64; NUM_JOINTS], torques: &[f64; NUM_JOINTS]) -> RobotState {
        let r = &self.robot;
        let quat = r.base_quat_wxyz();
        let a = r.layout.root_dof_adr;
        let qvel = r.data().qvel();
        let v_world = [qvel[a], qvel[a + 1], qvel[a + 2]];
        let [roll, pitch, _] = roll_pitch_yaw(quat);
        let qd = r.layout.joint_vel(qvel);
        let dt = self.cfg.control.policy_dt_s();
        let mut s = RobotState {
            base_lin_vel_body_mps: rotate_inverse(quat, v_world),
            base_ang_vel_body_rad_s: [qvel[a + 3], qvel[a + 4], qvel[a + 5]],
            gravity_body: rotate_inverse(quat, [0.0, 0.0, -1.0]),
            roll_rad: roll,
            pitch_rad: pitch,
            q_rad: r.layout.joint_pos(r.data().qpos()),
            qd_rad_s: qd,
            qdd_rad_s2: std::array::from_fn(|i| (qd[i] - qd_before[i]) / dt),
            torques_nm: *torques,
            ..Default::default()
        };
        let mut penalised = [false; 64];
        for c in r.data().contacts() {
            for (g, other) in [(c.geom1, c.geom2), (c.geom2, c.geom1)] {
                let other_is_robot = !matches!(r.layout.geom_parts[other], Part::Other);
                if other_is_robot {
                    continue;
                }
                match r.layout.geom_parts[g] {
                    Part::Foot(leg) => s.foot_contact[leg] = true,
                    Part::Trunk | Part::Thigh | Part::Calf => {
                        if g < penalised.len() && !penalised[g] {
                            penalised[g] = true;
                            s.penalised_contacts += 1;
                        }
                        if r.layout.geom_parts[g] == Part::Trunk && r.model().geom_body(other) == 0
                        {
                            s.trunk_on_ground = true;
                        }
                    }
                    _ => {}
                }
            }
        }
        s
    }

    /// The privileged group's contents now (physical units).
    pub fn privileged_state(&self) -> PrivilegedState {
        let base = self.robot.base_pos_m();
        let feet = self.robot.layout.foot_geoms;
        let xpos = self.robot.data().geom_xpos();
        let ground = |x: f64, y: f64| self.terrain.as_ref().map_or(0.0, |t| t.height_at(x, y));
        PrivilegedState {
            draw: self.draw,
            push_force_world_n: self.push_force_now_n,
            push_kick_world_mps: self.kick_now_mps,
            base_lin_vel_body_mps: self.state.base_lin_vel_body_mps,
            ground_under_feet_minus_base_z_m: std::array::from_fn(|leg| {
                let p = xpos[feet[leg]];
                ground(p[0], p[1]) - base[2]
            }),
        }
    }

    /// The `history` group as it stands (newest first; empty when not configured).
    pub fn history(&self) -> &[f32] {
        &self.history
    }

    /// Writes the observation row: each configured group in order. The policy
    /// observation also enters the history (the robot's own noisy readings).
    fn observe(&mut self, out: &mut [f32]) {
        let rng = Some(&mut self.rng);
        write_observation(
            &self.state,
            &self.command,
            &self.action,
            &self.robot.default_q_rad,
            &self.cfg.observation,
            rng,
            &mut self.policy_obs,
        );
        if !self.history.is_empty() {
            let n = self.history.len();
            self.history.copy_within(0..n - OBS_DIM, OBS_DIM);
            self.history[..OBS_DIM].copy_from_slice(&self.policy_obs);
        }
        let mut at = 0;
        for &g in &self.cfg.observation.groups {
            let w = g.width(self.cfg.observation.history_steps);
            let dst = &mut out[at..at + w];
            match g {
                ObsGroup::Policy => dst.copy_from_slice(&self.policy_obs),
                ObsGroup::Privileged => self.privileged_state().write(dst),
                ObsGroup::Extrinsics => self.privileged_state().write_extrinsics(dst),
                ObsGroup::History => dst.copy_from_slice(&self.history),
            }
            at += w;
        }
        debug_assert_eq!(at, out.len());
    }
}

/// Tag of [`Env::snapshot`]'s layout.
const ENV_SNAPSHOT_TAG: &str = "rall-env-2";

impl Env {
    /// The env's whole episode state between two steps (RNG, draw, command,
    /// actions, counters, history, running sums, MuJoCo state), for a resume
    /// that continues every episode bit for bit ([`Env::restore`]).
    pub fn snapshot(&self, w: &mut StateWriter) {
        w.str(ENV_SNAPSHOT_TAG);
        w.rng(&self.rng);
        let d = &self.draw;
        w.u64(d.friction.is_some() as u64);
        w.f64(d.friction.unwrap_or(0.0));
        w.f64(d.added_base_mass_kg);
        w.f64s(&d.motor_strength);
        w.f64s(&[d.kp_factor, d.kd_factor]);
        w.f64s(&d.com_offset_m);
        w.f64s(&self.command);
        w.f32s(&self.action);
        w.f32s(&self.previous_action);
        w.f64s(&self.previous_torques_nm);
        w.f64s(&self.feet_air_time_s);
        for v in [self.step_in_episode, self.terrain_level, self.terrain_type] {
            w.usize(v);
        }
        w.f64s(&self.spawn_xy_m);
        w.f64s(&self.force_push.force_n);
        w.usize(self.force_push.steps_left);
        w.f64s(&self.push_force_now_n);
        w.f64s(&self.kick_now_mps);
        w.f32s(&self.policy_obs);
        w.f32s(&self.history);
        w.f64(self.commanded_distance_m);
        self.snapshot_sums(w);
        w.usize(self.recent_firings.len());
        for &(term, step) in &self.recent_firings {
            w.usize(term);
            w.usize(step);
        }
        w.u64(self.instabilities);
        w.f64s(&self.robot.data().physics_state());
    }

    fn snapshot_sums(&self, w: &mut StateWriter) {
        let s = &self.sums;
        w.f64s(&s.reward_terms);
        w.f64s(&[
            s.risk_penalty,
            s.total_reward,
            s.distance_m,
            s.commanded_distance_m,
        ]);
        for v in s.risk_exceeded.iter().chain(&s.risk_fired) {
            w.u64(*v as u64);
        }
        w.usize(s.terrain_level);
        w.usize(s.steps);
    }

    /// Restores [`Env::snapshot`] (an env of the same config and model).
    pub fn restore(&mut self, r: &mut StateReader) -> anyhow::Result<()> {
        anyhow::ensure!(
            r.bytes()? == ENV_SNAPSHOT_TAG.as_bytes(),
            "env {}: not an env snapshot of this build's layout",
            self.index
        );
        self.rng = r.rng()?;
        let friction = (r.u64()? != 0, r.f64()?);
        let mut draw = EpisodeDraw {
            friction: friction.0.then_some(friction.1),
            added_base_mass_kg: r.f64()?,
            ..EpisodeDraw::default()
        };
        r.f64s_into(&mut draw.motor_strength, "motor strength")?;
        let mut gains = [0.0; 2];
        r.f64s_into(&mut gains, "gain factors")?;
        (draw.kp_factor, draw.kd_factor) = (gains[0], gains[1]);
        r.f64s_into(&mut draw.com_offset_m, "com offset")?;
        self.apply_draw(draw);
        r.f64s_into(&mut self.command, "command")?;
        r.f32s_into(&mut self.action, "action")?;
        r.f32s_into(&mut self.previous_action, "previous action")?;
        r.f64s_into(&mut self.previous_torques_nm, "previous torques")?;
        r.f64s_into(&mut self.feet_air_time_s, "feet air time")?;
        self.step_in_episode = r.usize()?;
        self.terrain_level = r.usize()?;
        self.terrain_type = r.usize()?;
        r.f64s_into(&mut self.spawn_xy_m, "spawn point")?;
        r.f64s_into(&mut self.force_push.force_n, "push force")?;
        self.force_push.steps_left = r.usize()?;
        r.f64s_into(&mut self.push_force_now_n, "push force now")?;
        r.f64s_into(&mut self.kick_now_mps, "kick now")?;
        r.f32s_into(&mut self.policy_obs, "policy observation")?;
        r.f32s_into(&mut self.history, "history")?;
        self.commanded_distance_m = r.f64()?;
        self.restore_sums(r)?;
        let n = r.usize()?;
        anyhow::ensure!(
            n <= NUM_RISK_TERMS * (self.fall_window_steps() + 1),
            "env {}: {n} recent risk firings cannot fit in the fall window",
            self.index
        );
        self.recent_firings.clear();
        for _ in 0..n {
            let (term, step) = (r.usize()?, r.usize()?);
            anyhow::ensure!(
                term < NUM_RISK_TERMS,
                "env {}: risk term {term}",
                self.index
            );
            self.recent_firings.push((term, step));
        }
        self.instabilities = r.u64()?;
        let physics = r.f64s()?;
        self.robot.set_physics_state(&physics)?;
        Ok(())
    }

    fn restore_sums(&mut self, r: &mut StateReader) -> anyhow::Result<()> {
        let s = &mut self.sums;
        r.f64s_into(&mut s.reward_terms, "reward sums")?;
        let mut f = [0.0; 4];
        r.f64s_into(&mut f, "episode sums")?;
        [
            s.risk_penalty,
            s.total_reward,
            s.distance_m,
            s.commanded_distance_m,
        ] = f;
        for v in s.risk_exceeded.iter_mut().chain(s.risk_fired.iter_mut()) {
            *v = u32::try_from(r.u64()?)?;
        }
        s.terrain_level = r.usize()?;
        s.steps = r.usize()?;
        Ok(())
    }
}

fn empty_summary(env_index: usize) -> EpisodeSummary {
    EpisodeSummary {
        env_index,
        steps: 0,
        end: EpisodeEnd::TimeOut,
        reward_terms: [0.0; NUM_REWARD_TERMS],
        risk_penalty: 0.0,
        total_reward: 0.0,
        risk_exceeded: [0; NUM_RISK_TERMS],
        risk_fired: [0; NUM_RISK_TERMS],
        risk_fired_before_fall: [0; NUM_RISK_TERMS],
        terrain_level: 0,
        distance_m: 0.0,
        commanded_distance_m: 0.0,
    }
}
