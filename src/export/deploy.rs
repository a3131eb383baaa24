//! The sidecar's deployment sections: what a controller must reproduce besides
//! the network (commands, start state, safety stop, sensing, the training
//! envelope) and a nominal closed-loop trace to check a control loop against.

use std::sync::Arc;

use anyhow::Result;
use serde_json::{json, Map, Value};

use crate::config::TrainConfig;
use crate::env::config::{PushConfig, RandomizationConfig};
use crate::env::terrain::{Terrain, TerrainKind};
use crate::env::{build_scene, Env, EnvConfig};
use crate::eval::ground::RoughParams;
use crate::learn::Learner;
use crate::robot::Robot;
use crate::sim::ObjKind;

/// Policy steps in the nominal trace.
pub const TRACE_STEPS: usize = 100;
/// The trace's command (vx m/s, vy m/s, yaw rate rad/s).
pub const TRACE_COMMAND: [f64; 3] = [0.5, 0.0, 0.0];
/// The flat ground rall adds to the robot MJCF (the `terrain` geom of a flat scene).
pub const FLAT_GROUND_XML: &str = "<worldbody><geom name=\"terrain\" type=\"plane\" size=\"0 0 0.05\" contype=\"0\" conaffinity=\"1\" condim=\"3\" friction=\"1.0 0.005 0.0001\"/></worldbody>";

/// The MJCF actuator driving each joint, in the sidecar's joint order.
pub fn actuator_names(robot: &Robot) -> Vec<String> {
    let model = robot.model();
    robot
        .layout
        .actuator_ids
        .iter()
        .map(|&a| model.name(ObjKind::Actuator, a).to_string())
        .collect()
}

/// The commands section: ranges, resampling and the zero threshold.
fn commands_json(env: &EnvConfig) -> Value {
    let c = &env.commands;
    let every = (c.resample_interval_s / env.control.policy_dt_s())
        .round()
        .max(1.0);
    json!({
        "vx_mps": c.vx_mps,
        "vy_mps": c.vy_mps,
        "yaw_rate_rad_s": c.yaw_rate_rad_s,
        "sampling": "each of vx, vy, yaw rate uniform in its range, drawn at the start of an episode and at every resample",
        "resample_interval_s": c.resample_interval_s,
        "resample_rule": format!("a new command every {every} policy steps of the episode (round(resample_interval_s / policy_dt_s)), the first at step {every}"),
        "zero_below_mps": c.zero_below_mps,
        "zero_rule": "after drawing: when hypot(vx, vy) < zero_below_mps, vx = vy = 0 (standing still is trained); the yaw rate is kept",
        "zero_threshold_applies_to_yaw": false,
    })
}

/// The start state: the keyframe pose at rest.
fn start_state_json(env: &EnvConfig, robot: &Robot) -> Value {
    json!({
        "source": format!("keyframe `{}` of {}", env.control.default_keyframe, env.robot_mjcf),
        "base_pos_m": robot.base_pos_m(),
        "base_quat_wxyz": robot.base_quat_wxyz(),
        "joint_angles_rad": robot.default_q_rad,
        "base_and_joint_velocities": "all zero",
        "previous_action": "zeros",
        "placement": "on flat ground at the origin; on rough ground rall lifts the keyframe by the tile's origin height",
    })
}

fn safety_stop_json(env: &EnvConfig) -> Value {
    let e = &env.episode;
    json!({
        "max_tilt_rad": e.max_tilt_rad,
        "tilt_rule": "stop when |roll| or |pitch| of the trunk (roll-pitch-yaw of its quaternion) exceeds max_tilt_rad, checked after every policy step",
        "trunk_contact": e.terminate_on_trunk_contact,
        "trunk_contact_rule": "stop when a trunk geom touches anything outside the robot (thigh and calf contacts are only penalised in training)",
        "in_training": "both end the episode (a fall); the robot is reset to start_state",
    })
}

/// What the policy was trained to sense (checked against `Env::measure` and `observe`).
fn sensing_json(env: &EnvConfig) -> Value {
    json!({
        "base_velocity": "ground truth from the simulator (the trunk frame's linear velocity, rotated into the trunk frame) plus Gaussian noise; no estimator was in the loop, so a robot needs a state estimator whose error is within the training noise",
        "noise": format!("Gaussian, std = observation.fields[].noise_std_physical_units x observation.noise_level ({}), drawn independently per value and step; commands and previous_action are never noised", env.observation.noise_level),
        "latency": "none: the observation is measured at the end of a policy step and its action drives the very next physics step",
        "actuation": "ideal torque motors (MJCF `motor`, no motor dynamics, no friction model in the joints beyond the MJCF); the PD law runs every physics step with fresh q, qdot",
        "observation_delay_steps": 0,
        "action_delay_steps": 0,
    })
}

/// The training envelope: terrain, randomisation and episode settings, as rall's
/// config tables (`[env.terrain]`, `[env.randomization]`) in JSON.
fn envelope_json(env: &EnvConfig) -> Result<Value> {
    Ok(json!({
        "terrain": serde_json::to_value(&env.terrain)?,
        "randomization": serde_json::to_value(&env.randomization)?,
        "episode_length_s": env.episode.length_s,
        "randomize_initial_episode_progress": env.episode.randomize_initial_length,
        "note": "friction and added_base_mass_kg are U[lo, hi] per episode (null: the MJCF's own); outside these the policy was never trained",
    }))
}

/// The deployment sections of the sidecar, keyed by section name.
pub fn deployment_sections(config: &TrainConfig, robot: &Robot) -> Result<Map<String, Value>> {
    let env = &config.env;
    let mut m = Map::new();
    m.insert("robot_mjcf".into(), json!(env.robot_mjcf));
    m.insert("commands".into(), commands_json(env));
    m.insert("start_state".into(), start_state_json(env, robot));
    m.insert("safety_stop".into(), safety_stop_json(env));
    m.insert("sensing".into(), sensing_json(env));
    m.insert("training_envelope".into(), envelope_json(env)?);
    Ok(m)
}

/// Seen on one control loop on a heightfield: the share of episodes that fell in
/// MuJoCo 4.0, and in MuJoCo 2.2.2 (rall's), in percent.
const HEIGHTFIELD_FALLS_PCT: [f64; 2] = [53.0, 7.0];

/// The simulator section: the MuJoCo version rall links (read from the library
/// at run time), a note on heightfields across versions, and the generators of
/// the grounds: the training ground of `config` (`terrain`: the generated
/// terrain of a rough config) and rall's rough evaluation ground.
pub fn simulator_json(config: &TrainConfig, terrain: Option<&Terrain>) -> Result<Value> {
    let version = crate::sim::mujoco_version_string();
    let [newer, ours] = HEIGHTFIELD_FALLS_PCT;
    Ok(json!({
        "engine": "MuJoCo",
        "mujoco_version": version,
        "mujoco_version_number": crate::sim::mujoco_version(),
        "statement": format!("trained and checked (`trace`, `command_envelope`) in MuJoCo {version}, read from the library rall linked when it exported this policy"),
        "heightfield_note": format!("heightfield contacts differ between MuJoCo versions: one control loop on a heightfield fell in {newer:.0}% of episodes in MuJoCo 4.0 where MuJoCo 2.2.2 fell in {ours:.0}%. Sim-to-sim checks on rough ground should use MuJoCo {version}; the flat-ground trace (a plane) is replayed in a newer pip MuJoCo by tests/check_trace.py"),
        "training_ground": training_ground_json(config, terrain)?,
        "rough_ground": rough_ground_json(),
        "heightfield_layout": "MuJoCo hfield: heights in metres on a grid of samples horizontal_scale_m apart, row r along y and column c along x, data[r * ncol + c] at x = -size[0] + c * horizontal_scale_m, y = -size[1] + r * horizontal_scale_m from the geom's position; the geom sits at the grid centre with z = the lowest height, size = (half extent x, half extent y, highest - lowest, base depth); rall uploads (z - lowest) / (highest - lowest)",
    }))
}

/// The ground `config` was trained on: a plane, or the tiled heightfield with
/// its generator, resolution, quantum and seed convention.
fn training_ground_json(config: &TrainConfig, terrain: Option<&Terrain>) -> Result<Value> {
    let t = &config.env.terrain;
    let Some(terrain) = terrain.filter(|_| t.kind == TerrainKind::Rough) else {
        return Ok(json!({
            "kind": "flat",
            "generator": "none: a plane",
            "ground_xml": FLAT_GROUND_XML,
        }));
    };
    let scene = terrain.scene_xml("</mujoco>").map_err(anyhow::Error::msg)?;
    let (nx, ny) = terrain.grid_shape();
    Ok(json!({
        "kind": "rough",
        "generator": "rall's tiled terrain (src/env/terrain.rs, Terrain::generate): legged_gym's terrain curriculum in kind, not its code; tiles of tile_length_m x tile_width_m, rows = difficulty levels along x, columns = tile types along y (proportions), a flat border around them",
        "noise": "rough slope tiles: a pyramid of slope 0.4 d plus uniform noise, each point of a lattice about 0.2 m apart an integer k uniform in [-K, K] (K = round(amplitude / vertical_scale_m), amplitude 0.025 + 0.075 d m) times vertical_scale_m, bilinear between lattice points, none on the central platform; d = level / num_levels. The other tile types (smooth slopes, stairs, discrete blocks, flat) are as the module documentation of src/env/terrain.rs says",
        "horizontal_scale_m": t.horizontal_scale_m,
        "vertical_scale_m": t.vertical_scale_m,
        "quantisation": "every height rounded to a multiple of vertical_scale_m",
        "grid_samples_x_y": [nx, ny],
        "grid_origin_m": terrain.grid_origin_m(),
        "seed": terrain.seed(),
        "seed_convention": "seed = the run's runner.seed; tile (level i, type j) draws from rand_chacha 0.3's ChaCha8Rng::seed_from_u64(seed) with set_stream(i * num_types + j), through rand 0.8's gen_range",
        "config": serde_json::to_value(t)?,
        "ground_xml": scene.trim_end_matches("</mujoco>"),
    }))
}

/// rall's rough evaluation ground (`rough` scenarios, severity rungs).
fn rough_ground_json() -> Value {
    let p = RoughParams::default();
    json!({
        "generator": "rall's random rough ground (src/eval/ground.rs, Ground::rough): legged_gym's random_uniform_terrain in kind; the ground of `rall eval` scenarios with `rough` and of every severity rung",
        "noise": "uniform on a lattice: lattice points evenly spaced over the field, round(2 half_extent_m / lattice_m) + 1 per axis, each an integer k uniform in [-K, K] (K = round(amplitude_m / vertical_scale_m)) times vertical_scale_m; samples bilinear between lattice points, then rounded to vertical_scale_m; samples with |x| and |y| <= spawn_pad_m stay at 0",
        "horizontal_scale_m": p.horizontal_scale_m,
        "vertical_scale_m": p.vertical_scale_m,
        "params": p,
        "half_extent_rule": "half_extent_m = max(5, min(params.half_extent_m, hypot(max |vx|, max |vy| of commands) * episode_length_s + 3)), the field centred on the spawn point at the origin",
        "amplitude_rule": "params.amplitude_m by default; a severity rung sets it (rough_amplitude_m of experiments/severity-ladder.toml)",
        "seed_convention": "seed = the evaluation's --seed; the lattice draws x fastest then y, from rand_chacha 0.3's ChaCha8Rng::seed_from_u64(seed) through rand 0.8's gen_range",
        "mujoco": "an hfield geom named `ground` (a 0.5 m base, at least 0.001 m of elevation) with a plane 0.05 m under its lowest point as a safety net; friction 1.0 0.005 0.0001, condim 3",
    })
}

/// The trace's env: flat ground, the fixed command, no noise, no randomisation.
pub fn nominal_env(training: &EnvConfig) -> EnvConfig {
    let mut cfg = crate::eval::tracking::tracking_env(training);
    cfg.observation.noise_level = 0.0;
    cfg.randomization = RandomizationConfig {
        friction: None,
        added_base_mass_kg: None,
        motor_strength: None,
        kp_factor: None,
        kd_factor: None,
        com_offset_m: None,
        push: PushConfig::None,
    };
    let c = &mut cfg.commands;
    c.vx_mps = [TRACE_COMMAND[0]; 2];
    c.vy_mps = [TRACE_COMMAND[1]; 2];
    c.yaw_rate_rad_s = [TRACE_COMMAND[2]; 2];
    c.resample_interval_s = 1e3;
    cfg.episode.length_s = cfg
        .episode
        .length_s
        .max(TRACE_STEPS as f64 * cfg.control.policy_dt_s() * 2.0);
    cfg
}

/// Rows of the nominal closed-loop trace, one per policy step.
#[derive(Debug, Default, Clone)]
pub struct Trace {
    pub obs: Vec<Vec<f32>>,
    pub actions: Vec<Vec<f32>>,
    pub targets_rad: Vec<Vec<f64>>,
    pub torques_nm: Vec<Vec<f64>>,
    pub base_lin_vel_body_mps: Vec<[f64; 3]>,
    pub base_pos_m: Vec<[f64; 3]>,
    pub joint_pos_rad: Vec<Vec<f64>>,
    /// The policy step whose physics ended the episode (a fall), when one did;
    /// the rows stop before it.
    pub fell_at_step: Option<usize>,
}

/// `steps` policy steps of `learner`'s mean from the start state in [`nominal_env`].
pub fn nominal_trace(learner: &Learner, training: &EnvConfig, steps: usize) -> Result<Trace> {
    let cfg = nominal_env(training);
    let scene = build_scene(&cfg, 0)?;
    let mut env = Env::new(Arc::new(cfg.clone()), &scene.model, None, 0, 0)?;
    let w = env.obs_width();
    let (mut obs, mut final_obs) = (vec![0.0f32; w], vec![0.0f32; w]);
    env.reset(&mut obs)?;
    let mut t = Trace::default();
    for step in 0..steps {
        let action = learner.act_mean(&obs);
        let targets = cfg
            .control
            .joint_targets(&env.robot().default_q_rad, &action);
        t.obs.push(obs[..crate::env::OBS_DIM].to_vec());
        t.actions.push(action.clone());
        t.targets_rad.push(targets.to_vec());
        if env.step(&action, &mut obs, &mut final_obs).done {
            // a policy that falls keeps the steps before its fall (the last row is the
            // step that ended it; the env has reset since, so nothing of it is recorded)
            t.obs.pop();
            t.actions.pop();
            t.targets_rad.pop();
            t.fell_at_step = Some(step);
            break;
        }
        let s = env.state();
        t.torques_nm.push(s.torques_nm.to_vec());
        t.base_lin_vel_body_mps.push(s.base_lin_vel_body_mps);
        t.base_pos_m.push(env.robot().base_pos_m());
        t.joint_pos_rad.push(s.q_rad.to_vec());
    }
    Ok(t)
}

/// The trace section of the sidecar.
pub fn trace_json(t: &Trace, control: &crate::robot::ControlConfig) -> Value {
    json!({
        "purpose": "the check for a deployment loop: run your control loop (observation builder, network, action law, PD) in MuJoCo from start_state under `command` and compare, step by step, with these rows. `python3 tests/check_onnx.py` does this with pip mujoco and onnxruntime",
        "conditions": {
            "command": TRACE_COMMAND,
            "command_resampling": "none (the command is held for the whole trace)",
            "ground": "flat: the robot MJCF with `ground_xml` inserted before its closing </mujoco>",
            "ground_xml": FLAT_GROUND_XML,
            "noise": "none",
            "friction_and_mass": "nominal (the MJCF's own; no randomisation, no pushes)",
            "start": "start_state",
            "physics_dt_s": control.physics_dt_s,
            "decimation": control.decimation,
        },
        "steps": t.obs.len(),
        "row_k": "obs[k] is observed before policy step k (row 0 at start_state), actions[k] = onnx(obs[k]), joint_targets_rad[k] the targets it sets; torques_nm[k] (the last physics sub-step's), base_lin_vel_body_mps[k], base_pos_m[k] and joint_pos_rad[k] are measured after that step's physics",
        "obs": t.obs,
        "actions": t.actions,
        "joint_targets_rad": t.targets_rad,
        "torques_nm": t.torques_nm,
        "base_lin_vel_body_mps": t.base_lin_vel_body_mps,
        "base_pos_m": t.base_pos_m,
        "joint_pos_rad": t.joint_pos_rad,
    })
}
