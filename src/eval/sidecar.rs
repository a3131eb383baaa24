//! Reading a policy's JSON sidecar (written by `rall export`, or by hand for a
//! policy trained elsewhere, see docs/outside-policies.md) into the env config
//! rall runs it in and the map from rall's observation row to the network's input.
//!
//! Every value rall cannot produce is refused with the sidecar field that asks
//! for it: an observation field rall does not measure, per-element scales rall
//! does not apply, joints in another order, a default pose other than the
//! robot's keyframe.

use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use serde_json::Value;

use crate::env::observation::{ObsGroup, OBS_LAYOUT};
use crate::env::{build_scene, EnvConfig, ACT_DIM};
use crate::robot::{Robot, NUM_JOINTS};

/// Sidecar format name.
pub const SIDECAR_FORMAT: &str = "rall-onnx-sidecar";

/// What a sidecar tells rall: the env to run the policy in, and for each value of
/// the network's `obs` input, the column of rall's observation row it is.
#[derive(Debug, Clone)]
pub struct SidecarPolicy {
    pub env: EnvConfig,
    /// `input[k] = rall_obs[input_columns[k]]`.
    pub input_columns: Vec<usize>,
    /// The robot joint of the network's joint `k` (`joints.names` order), so
    /// `rall_action[joint_order[k]] = output[k]`; the identity in rall's own order.
    pub joint_order: Vec<usize>,
    /// Sections absent from the sidecar, filled with rall's defaults.
    pub defaulted: Vec<&'static str>,
}

/// The value at a `/`-separated path, or an error naming it.
fn at<'a>(side: &'a Value, path: &str) -> Result<&'a Value> {
    let mut v = side;
    for key in path.split('.') {
        v = v
            .get(key)
            .with_context(|| format!("sidecar field `{path}` is missing"))?;
    }
    Ok(v)
}

fn num(side: &Value, path: &str) -> Result<f64> {
    at(side, path)?
        .as_f64()
        .filter(|v| v.is_finite())
        .with_context(|| format!("sidecar field `{path}` must be a finite number"))
}

fn nums(v: &Value, path: &str) -> Result<Vec<f64>> {
    let arr = v
        .as_array()
        .with_context(|| format!("sidecar field `{path}` must be an array of numbers"))?;
    arr.iter()
        .map(|x| {
            x.as_f64()
                .filter(|v| v.is_finite())
                .with_context(|| format!("sidecar field `{path}` must hold finite numbers"))
        })
        .collect()
}

fn range(side: &Value, path: &str) -> Result<[f64; 2]> {
    let v = nums(at(side, path)?, path)?;
    ensure!(
        v.len() == 2 && v[0] <= v[1],
        "sidecar field `{path}` must be [lo, hi] with lo <= hi, got {v:?}"
    );
    Ok([v[0], v[1]])
}

/// The one value of a field's per-element `scale` (rall scales a group alike).
fn uniform(values: &[f64], path: &str) -> Result<f64> {
    let first = *values
        .first()
        .with_context(|| format!("sidecar field `{path}` is empty"))?;
    ensure!(
        values.iter().all(|&v| v == first),
        "sidecar field `{path}` = {values:?}: rall applies one scale to the whole field"
    );
    Ok(first)
}

/// Reads `path` (a JSON sidecar) into the env config and input map rall runs the policy with.
pub fn read_sidecar(path: &Path) -> Result<SidecarPolicy> {
    let text = std::fs::read_to_string(path).with_context(|| {
        format!(
            "reading the sidecar {} (an ONNX policy needs its JSON sidecar beside it, same name)",
            path.display()
        )
    })?;
    let side: Value = serde_json::from_str(&text)
        .with_context(|| format!("{} is not valid JSON", path.display()))?;
    sidecar_policy(&side).with_context(|| format!("sidecar {}", path.display()))
}

/// [`read_sidecar`] of parsed JSON.
pub fn sidecar_policy(side: &Value) -> Result<SidecarPolicy> {
    let format = at(side, "format")?.as_str().unwrap_or_default();
    ensure!(
        format == SIDECAR_FORMAT,
        "sidecar field `format` is {format:?}, expected {SIDECAR_FORMAT:?}"
    );
    let mut env = EnvConfig::default();
    let mut defaulted = Vec::new();
    if let Some(m) = side.get("robot_mjcf") {
        env.robot_mjcf = m
            .as_str()
            .context("sidecar field `robot_mjcf` must be a string")?
            .to_string();
    }
    read_control(side, &mut env)?;
    let joint_order = joint_order(side, &env)?;
    let input_columns = read_observation(side, &mut env, &joint_order)?;
    if side.get("commands").is_some() {
        read_commands(side, &mut env)?;
    } else {
        defaulted.push("commands");
    }
    if side.get("safety_stop").is_some() {
        env.episode.max_tilt_rad = num(side, "safety_stop.max_tilt_rad")?;
        env.episode.terminate_on_trunk_contact =
            at(side, "safety_stop.trunk_contact")?
                .as_bool()
                .context("sidecar field `safety_stop.trunk_contact` must be true or false")?;
    } else {
        defaulted.push("safety_stop");
    }
    if side.get("training_envelope").is_some() {
        read_envelope(side, &mut env)?;
    } else {
        defaulted.push("training_envelope");
    }
    env.validate()
        .map_err(|e| anyhow::anyhow!("the sidecar gives an impossible env: {e}"))?;
    Ok(SidecarPolicy {
        env,
        input_columns,
        joint_order,
        defaulted,
    })
}

/// PD gains, action law and rates.
fn read_control(side: &Value, env: &mut EnvConfig) -> Result<()> {
    let c = &mut env.control;
    c.kp_nm_per_rad = num(side, "pd.kp_nm_per_rad")?;
    c.kd_nm_s_per_rad = num(side, "pd.kd_nm_s_per_rad")?;
    c.action_scale_rad = num(side, "action.scale_rad")?;
    c.clip_actions = num(side, "action.clip")?;
    c.physics_dt_s = num(side, "rates.physics_dt_s")?;
    let decimation = num(side, "rates.decimation")?;
    ensure!(
        decimation >= 1.0 && decimation.fract() == 0.0,
        "sidecar field `rates.decimation` must be a whole number >= 1, got {decimation}"
    );
    c.decimation = decimation as usize;
    let dim = num(side, "action.dim")?;
    ensure!(
        dim == ACT_DIM as f64,
        "sidecar field `action.dim` is {dim}: rall's robot has {ACT_DIM} motors"
    );
    if let Some(k) = side.get("joints").and_then(|j| j.get("keyframe")) {
        c.default_keyframe = k
            .as_str()
            .context("sidecar field `joints.keyframe` must be a string")?
            .to_string();
    }
    // torque limits by joint name: one per motor kind (hip, thigh, calf)
    let limits = at(side, "pd.torque_limits_nm")?
        .as_object()
        .context("sidecar field `pd.torque_limits_nm` must map joint names to N m")?;
    for (kind, slot) in ["hip", "thigh", "calf"].iter().zip(0..3) {
        let of_kind: Vec<(&String, f64)> = limits
            .iter()
            .filter(|(n, _)| n.ends_with(&format!("_{kind}_joint")))
            .map(|(n, v)| (n, v.as_f64().unwrap_or(f64::NAN)))
            .collect();
        ensure!(
            of_kind.len() == 4,
            "sidecar field `pd.torque_limits_nm` must name the four {kind} joints (FR_{kind}_joint, ...), found {}",
            of_kind.len()
        );
        let v = of_kind[0].1;
        ensure!(
            of_kind.iter().all(|(_, x)| *x == v) && v.is_finite() && v > 0.0,
            "sidecar field `pd.torque_limits_nm`: rall limits every {kind} motor alike, got {of_kind:?}"
        );
        c.torque_limits_nm[slot] = v;
    }
    Ok(())
}

/// Scales, clip and noise per field; the columns of rall's row the input takes.
fn read_observation(side: &Value, env: &mut EnvConfig, joints: &[usize]) -> Result<Vec<usize>> {
    let o = &mut env.observation;
    o.groups = vec![ObsGroup::Policy];
    o.clip = num(side, "observation.clip")?;
    let level = side
        .get("observation")
        .and_then(|v| v.get("noise_level"))
        .map(|_| num(side, "observation.noise_level"))
        .transpose()?;
    o.noise_level = level.unwrap_or(1.0);
    let fields = at(side, "observation.fields")?
        .as_array()
        .context("sidecar field `observation.fields` must be an array")?;
    let mut columns = Vec::new();
    for (k, f) in fields.iter().enumerate() {
        let here = format!("observation.fields[{k}]");
        let name = f
            .get("name")
            .and_then(Value::as_str)
            .with_context(|| format!("sidecar field `{here}.name` is missing"))?;
        let (offset, len) = rall_field(name).with_context(|| {
            format!(
                "sidecar field `{here}.name` = {name:?}: rall cannot produce this observation; it measures {}",
                OBS_LAYOUT.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", ")
            )
        })?;
        let given_len = num(f, "length").with_context(|| format!("in `{here}`"))?;
        ensure!(
            given_len == len as f64,
            "sidecar field `{here}.length` = {given_len}: rall's {name} has {len} values"
        );
        ensure!(
            !columns.contains(&offset) && !columns.contains(&(offset + len - 1)),
            "sidecar field `{here}.name`: {name} is listed twice"
        );
        if let Some(off) = f.get("offset") {
            ensure!(
                off.as_f64() == Some(columns.len() as f64),
                "sidecar field `{here}.offset` = {off}: the fields must follow each other, this one starts at {}",
                columns.len()
            );
        }
        let scale = nums(
            f.get("scale")
                .with_context(|| format!("sidecar field `{here}.scale` is missing"))?,
            &format!("{here}.scale"),
        )?;
        ensure!(
            scale.len() == len,
            "sidecar field `{here}.scale` has {} values, {name} has {len}",
            scale.len()
        );
        let noise = field_noise(f, &here, level)?;
        set_field(o, name, &scale, noise, &here)?;
        if len == NUM_JOINTS && name != "command_vx_vy_yaw" {
            // per-joint fields follow the sidecar's joint order
            columns.extend(joints.iter().map(|&j| offset + j));
        } else {
            columns.extend(offset..offset + len);
        }
    }
    let dim = num(side, "observation.dim")?;
    ensure!(
        dim == columns.len() as f64,
        "sidecar field `observation.dim` = {dim} but the fields hold {} values",
        columns.len()
    );
    Ok(columns)
}

/// A field's observation-noise std in physical units, before `noise_level`.
fn field_noise(f: &Value, here: &str, level: Option<f64>) -> Result<f64> {
    let get = |key: &str| -> Result<Option<f64>> {
        f.get(key)
            .map(|v| {
                v.as_f64()
                    .filter(|x| x.is_finite() && *x >= 0.0)
                    .with_context(|| format!("sidecar field `{here}.{key}` must be a number >= 0"))
            })
            .transpose()
    };
    // rall's own export states both the std and the level; a hand-written
    // sidecar the product alone (level 1)
    Ok(match (get("noise_std_physical_units")?, level) {
        (Some(n), Some(_)) => n,
        _ => get("training_noise_std_physical_units")?.unwrap_or(0.0),
    })
}

/// Offset and length of an observation field in rall's row.
fn rall_field(name: &str) -> Option<(usize, usize)> {
    let mut offset = 0;
    for (n, len) in OBS_LAYOUT {
        if n == name {
            return Some((offset, len));
        }
        offset += len;
    }
    None
}

fn set_field(
    o: &mut crate::env::config::ObservationConfig,
    name: &str,
    scale: &[f64],
    noise: f64,
    here: &str,
) -> Result<()> {
    let s = &mut o.scales;
    let n = &mut o.noise_std;
    let path = format!("{here}.scale");
    let (scale_slot, noise_slot) = match name {
        "base_lin_vel_body" => (&mut s.lin_vel, &mut n.lin_vel),
        "base_ang_vel_body" => (&mut s.ang_vel, &mut n.ang_vel),
        "gravity_body" => (&mut s.gravity, &mut n.gravity),
        "joint_pos_minus_default" => (&mut s.dof_pos, &mut n.dof_pos),
        "joint_vel" => (&mut s.dof_vel, &mut n.dof_vel),
        "command_vx_vy_yaw" => {
            o.command_scale = [scale[0], scale[1], scale[2]];
            ensure!(
                noise == 0.0,
                "sidecar field `{here}`: rall never adds noise to the command"
            );
            return Ok(());
        }
        "previous_action" => {
            ensure!(
                scale.iter().all(|&v| v == 1.0),
                "sidecar field `{path}` = {scale:?}: rall feeds the previous raw action unscaled (1)"
            );
            ensure!(
                noise == 0.0,
                "sidecar field `{here}`: rall never adds noise to the previous action"
            );
            return Ok(());
        }
        other => bail!("sidecar field `{here}.name` = {other:?}: no scale in rall"),
    };
    *scale_slot = uniform(scale, &path)?;
    *noise_slot = noise;
    Ok(())
}

fn read_commands(side: &Value, env: &mut EnvConfig) -> Result<()> {
    let c = &mut env.commands;
    c.vx_mps = range(side, "commands.vx_mps")?;
    c.vy_mps = range(side, "commands.vy_mps")?;
    c.yaw_rate_rad_s = range(side, "commands.yaw_rate_rad_s")?;
    c.resample_interval_s = num(side, "commands.resample_interval_s")?;
    c.zero_below_mps = num(side, "commands.zero_below_mps")?;
    if let Some(yaw) = side["commands"].get("zero_threshold_applies_to_yaw") {
        ensure!(
            yaw.as_bool() == Some(false),
            "sidecar field `commands.zero_threshold_applies_to_yaw`: rall zeroes the planar command only (false)"
        );
    }
    Ok(())
}

/// Terrain, randomisation and episode settings (rall's config tables as JSON).
fn read_envelope(side: &Value, env: &mut EnvConfig) -> Result<()> {
    let e = &side["training_envelope"];
    if let Some(r) = e.get("randomization") {
        env.randomization = serde_json::from_value(r.clone())
            .context("sidecar field `training_envelope.randomization`")?;
    }
    if let Some(t) = e.get("terrain") {
        env.terrain = serde_json::from_value(t.clone())
            .context("sidecar field `training_envelope.terrain`")?;
    }
    if let Some(ep) = e.get("episode_length_s") {
        env.episode.length_s = ep
            .as_f64()
            .context("sidecar field `training_envelope.episode_length_s` must be a number")?;
    }
    if let Some(r) = e.get("randomize_initial_episode_progress") {
        env.episode.randomize_initial_length = r.as_bool().context(
            "sidecar field `training_envelope.randomize_initial_episode_progress` must be true or false",
        )?;
    }
    Ok(())
}

/// The robot joint of each of the sidecar's joints (`joints.names`, each of the
/// robot's once, in any order), checked to stand at the keyframe's angles.
fn joint_order(side: &Value, env: &EnvConfig) -> Result<Vec<usize>> {
    let scene = build_scene(env, 0)?;
    let robot = Robot::new(scene.model.try_clone()?, env.control.clone())?;
    let names: Vec<String> = at(side, "joints.names")?
        .as_array()
        .context("sidecar field `joints.names` must be an array of strings")?
        .iter()
        .map(|v| v.as_str().unwrap_or_default().to_string())
        .collect();
    let robot_names = &robot.layout.joint_names;
    let mut order = Vec::with_capacity(NUM_JOINTS);
    for (k, n) in names.iter().enumerate() {
        let j = robot_names.iter().position(|r| r == n).with_context(|| {
            format!(
                "sidecar field `joints.names[{k}]` = {n:?}: rall's robot ({}) has no such joint; its joints are {robot_names:?}",
                env.robot_mjcf
            )
        })?;
        ensure!(
            !order.contains(&j),
            "sidecar field `joints.names[{k}]`: {n:?} is listed twice"
        );
        order.push(j);
    }
    ensure!(
        order.len() == NUM_JOINTS,
        "sidecar field `joints.names` names {} joints, the robot has {NUM_JOINTS}: {robot_names:?}",
        order.len()
    );
    let angles = nums(
        at(side, "joints.default_angles_rad_in_order")?,
        "joints.default_angles_rad_in_order",
    )?;
    ensure!(
        angles.len() == NUM_JOINTS,
        "sidecar field `joints.default_angles_rad_in_order` has {} angles, the robot {NUM_JOINTS}",
        angles.len()
    );
    for (i, (a, &j)) in angles.iter().zip(&order).enumerate() {
        let d = robot.default_q_rad[j];
        ensure!(
            (a - d).abs() <= 1e-6,
            "sidecar field `joints.default_angles_rad_in_order[{i}]` ({}) = {a} rad but keyframe `{}` of {} holds {d} rad: rall's default pose is the keyframe's",
            names[i],
            env.control.default_keyframe,
            env.robot_mjcf
        );
    }
    Ok(order)
}
