//! Reading a policy's JSON sidecar (written by `rall export`, or by hand for a
//! policy trained elsewhere, see docs/outside-policies.md) into the env config
//! rall runs it in and the map from rall's observation row to the network's input.
//!
//! Every value rall cannot produce is refused with the sidecar field that asks
//! for it: an observation field rall does not measure, per-element scales rall
//! does not apply, joints in another order, a default pose other than the
//! robot's keyframe.
//!
//! The sidecar is read strictly: a key rall does not know (a misspelt one would
//! silently take rall's default) is an error naming it and the nearest known
//! key, and a format version other than the one rall reads is refused. The
//! observation rows a sidecar carries (`reference.observations`, `trace.obs`)
//! are checked against the fields it declares, so fields listed in another
//! order than the network reads them are refused before any benchmark (the
//! network itself is run on `reference` by `eval::policy`).

use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use serde_json::Value;

use crate::env::observation::{ObsGroup, OBS_LAYOUT};
use crate::env::{build_scene, EnvConfig, ACT_DIM};
use crate::robot::{Robot, NUM_JOINTS};

/// Sidecar format name.
pub const SIDECAR_FORMAT: &str = "rall-onnx-sidecar";

/// The sidecar format version this rall reads (what `rall export` writes).
pub const SIDECAR_VERSION_READ: u64 = 2;

/// Default `reference.tolerance_abs`: what another runtime may differ by.
pub const DEFAULT_REFERENCE_TOLERANCE: f64 = 1e-4;

/// Keys each section of a sidecar may hold: those rall reads, and the
/// descriptions `rall export` writes beside them. The other top-level sections
/// (`checkpoint`, `onnx`, `network`, `sensing`, `start_state`, `trace`,
/// `history`, `control_loop`, `simulator`, `command_envelope`, `safety`)
/// describe an export; rall reads only `trace`'s rows.
const SECTION_KEYS: [(&str, &[&str]); 12] = [
    (
        "",
        &[
            "format",
            "format_version",
            "robot_mjcf",
            "observation",
            "joints",
            "action",
            "pd",
            "rates",
            "commands",
            "safety_stop",
            "training_envelope",
            "reference",
            "onnx_file",
            "checkpoint",
            "onnx",
            "network",
            "deployment_check",
            "control_loop",
            "sensing",
            "start_state",
            "trace",
            "history",
            "simulator",
            "command_envelope",
            "safety",
        ],
    ),
    (
        "observation",
        &[
            "dim",
            "clip",
            "fields",
            "noise_level",
            "order",
            "formula",
            "noise",
        ],
    ),
    (
        "observation.fields[]",
        &[
            "name",
            "length",
            "scale",
            "offset",
            "training_noise_std_physical_units",
            "noise_std_physical_units",
            "units",
            "definition",
        ],
    ),
    (
        "joints",
        &[
            "names",
            "default_angles_rad_in_order",
            "keyframe",
            "order",
            "default_angles_rad",
            "source",
            "mjcf_actuator_names",
            "mjcf_actuators",
            "torque_limits_nm",
        ],
    ),
    (
        "action",
        &["dim", "clip", "scale_rad", "target_law", "previous_action"],
    ),
    (
        "pd",
        &[
            "kp_nm_per_rad",
            "kd_nm_s_per_rad",
            "torque_limits_nm",
            "law",
            "on_motor_drivers",
        ],
    ),
    (
        "rates",
        &[
            "physics_dt_s",
            "decimation",
            "pd_rate_hz",
            "policy_dt_s",
            "policy_rate_hz",
        ],
    ),
    (
        "commands",
        &[
            "vx_mps",
            "vy_mps",
            "yaw_rate_rad_s",
            "resample_interval_s",
            "zero_below_mps",
            "zero_threshold_applies_to_yaw",
            "resample_rule",
            "sampling",
            "zero_rule",
        ],
    ),
    (
        "safety_stop",
        &[
            "max_tilt_rad",
            "trunk_contact",
            "in_training",
            "tilt_rule",
            "trunk_contact_rule",
        ],
    ),
    (
        "training_envelope",
        &[
            "episode_length_s",
            "randomization",
            "terrain",
            "randomize_initial_episode_progress",
            "note",
        ],
    ),
    (
        "reference",
        &[
            "observations",
            "actions",
            "tolerance_abs",
            "description",
            "history",
        ],
    ),
    (
        "trace",
        &[
            "purpose",
            "conditions",
            "row_k",
            "obs",
            "actions",
            "joint_targets_rad",
            "torques_nm",
            "base_lin_vel_body_mps",
            "base_pos_m",
            "joint_pos_rad",
            "steps",
        ],
    ),
];

/// Observation rows and the raw actions the network returns for them
/// (`reference`), each row as wide as the network's input.
#[derive(Debug, Clone)]
pub struct ReferencePairs {
    pub observations: Vec<f32>,
    pub actions: Vec<f32>,
    /// The largest difference allowed per action value.
    pub tolerance_abs: f64,
}

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
    /// `reference`'s pairs, when the sidecar has them: the network must
    /// reproduce them before it is benchmarked.
    pub reference: Option<ReferencePairs>,
}

/// Where a field of the network's input sits, as the sidecar declares it.
struct FieldSpan {
    /// Its index in `observation.fields`.
    index: usize,
    name: String,
    /// Its first value's index in the network's input row.
    at: usize,
    scale: Vec<f64>,
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
    check_version(side)?;
    check_known_keys(side)?;
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
    let (input_columns, spans) = read_observation(side, &mut env, &joint_order)?;
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
    let reference = read_reference(side)?;
    let rows = RowCheck {
        side,
        spans: &spans,
        width: input_columns.len(),
        clip: env.observation.clip,
    };
    if let Some(r) = &reference {
        rows.gravity_is_unit("reference.observations", &r.observations)?;
    }
    rows.trace_follows_fields(&env)?;
    Ok(SidecarPolicy {
        env,
        input_columns,
        joint_order,
        defaulted,
        reference,
    })
}

/// Refuses a `format_version` other than [`SIDECAR_VERSION_READ`].
fn check_version(side: &Value) -> Result<()> {
    let v = side.get("format_version").with_context(|| {
        format!("sidecar field `format_version` is missing (this rall reads format {SIDECAR_VERSION_READ})")
    })?;
    ensure!(
        v.as_u64() == Some(SIDECAR_VERSION_READ),
        "sidecar field `format_version` is {v}: this rall reads sidecar format {SIDECAR_VERSION_READ} only (what `rall export` writes; docs/outside-policies.md)"
    );
    Ok(())
}

/// Refuses any key a section does not hold ([`SECTION_KEYS`]), naming the
/// nearest key it does.
fn check_known_keys(side: &Value) -> Result<()> {
    for (section, keys) in SECTION_KEYS {
        if let Some(each) = section.strip_suffix("[]") {
            let items = side
                .pointer(&json_pointer(each))
                .and_then(Value::as_array)
                .into_iter()
                .flatten();
            for (k, item) in items.enumerate() {
                check_object_keys(item, &format!("{each}[{k}]"), keys)?;
            }
        } else if let Some(v) = side.pointer(&json_pointer(section)) {
            check_object_keys(v, section, keys)?;
        }
    }
    Ok(())
}

/// `a.b` as the JSON pointer `/a/b` (`""`: the whole document).
fn json_pointer(dotted: &str) -> String {
    dotted
        .split('.')
        .filter(|s| !s.is_empty())
        .fold(String::new(), |p, k| p + "/" + k)
}

/// Refuses a key of object `v` (at `path`) not among `keys`.
fn check_object_keys(v: &Value, path: &str, keys: &[&str]) -> Result<()> {
    let here = |key: &str| match path {
        "" => key.to_string(),
        p => format!("{p}.{key}"),
    };
    let obj = v
        .as_object()
        .with_context(|| format!("sidecar field `{path}` must be an object"))?;
    for key in obj.keys() {
        if !keys.contains(&key.as_str()) {
            let nearest = nearest_key(key, keys);
            bail!(
                "sidecar key `{}` is not one rall knows: did you mean `{}`? (a misspelt key would silently take rall's default)",
                here(key),
                here(nearest)
            );
        }
    }
    Ok(())
}

/// The key of `keys` nearest to `key`: the fewest edits to it or to its
/// beginning (so `kp` finds `kp_nm_per_rad`), then the fewest to the whole.
fn nearest_key<'a>(key: &str, keys: &[&'a str]) -> &'a str {
    let start = |k: &str| -> String { k.chars().take(key.chars().count()).collect() };
    keys.iter()
        .min_by_key(|k| {
            let whole = edit_distance(key, k);
            (whole.min(edit_distance(key, &start(k))), whole)
        })
        .copied()
        .unwrap_or_default()
}

/// Levenshtein distance between `a` and `b` (by characters).
fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut diagonal = row[0];
        row[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let next = (diagonal + usize::from(ca != *cb))
                .min(row[j] + 1)
                .min(row[j + 1] + 1);
            diagonal = row[j + 1];
            row[j + 1] = next;
        }
    }
    row[b.len()]
}

/// Rows of `path` (an array of arrays of numbers), flattened; each must hold
/// `width` values.
fn rows(side: &Value, path: &str, width: usize) -> Result<(Vec<f32>, usize)> {
    let (out, widths) = any_rows(side, path)?;
    if let Some((r, w)) = widths.iter().enumerate().find(|(_, w)| **w != width) {
        bail!("sidecar field `{path}[{r}]` has {w} values, expected {width}");
    }
    Ok((out, widths.len()))
}

/// Rows of `path` (an array of arrays of numbers), flattened, and each one's length.
fn any_rows(side: &Value, path: &str) -> Result<(Vec<f32>, Vec<usize>)> {
    let list = at(side, path)?
        .as_array()
        .with_context(|| format!("sidecar field `{path}` must be an array of rows"))?;
    let mut out = Vec::new();
    let mut widths = Vec::with_capacity(list.len());
    for (r, row) in list.iter().enumerate() {
        let values = nums(row, &format!("{path}[{r}]"))?;
        widths.push(values.len());
        out.extend(values.iter().map(|&v| v as f32));
    }
    Ok((out, widths))
}

/// Whether every row of `widths` holds `width` values.
fn all_of_width(widths: &[usize], width: usize) -> bool {
    widths.iter().all(|&w| w == width)
}

/// `reference`'s observation and action rows, when the sidecar has them (the
/// observations' width is checked against the network's input when it runs).
fn read_reference(side: &Value) -> Result<Option<ReferencePairs>> {
    let Some(r) = side.get("reference") else {
        return Ok(None);
    };
    if r.get("observations").is_none() && r.get("actions").is_none() {
        return Ok(None);
    }
    let (observations, widths) = any_rows(side, "reference.observations")?;
    let n = widths.len();
    ensure!(
        widths.first().is_none_or(|&w| all_of_width(&widths, w)),
        "sidecar field `reference.observations`: its rows must all be equally long, got lengths {widths:?}"
    );
    let (actions, m) = rows(side, "reference.actions", ACT_DIM)?;
    ensure!(
        n == m,
        "sidecar field `reference` holds {n} observations but {m} actions"
    );
    let tolerance_abs = match r.get("tolerance_abs") {
        Some(_) => num(side, "reference.tolerance_abs")?,
        None => DEFAULT_REFERENCE_TOLERANCE,
    };
    ensure!(
        tolerance_abs >= 0.0,
        "sidecar field `reference.tolerance_abs` must be >= 0, got {tolerance_abs}"
    );
    Ok(Some(ReferencePairs {
        observations,
        actions,
        tolerance_abs,
    }))
}

/// Checks observation rows a sidecar carries against the fields it declares.
struct RowCheck<'a> {
    side: &'a Value,
    spans: &'a [FieldSpan],
    /// Values per row (the network's input width).
    width: usize,
    clip: f64,
}

/// The gap allowed between a stored observation value and the one its state
/// gives (float32 rounding of both).
fn close(got: f64, want: f64) -> bool {
    (got - want).abs() <= 1e-4 * (1.0 + want.abs())
}

impl RowCheck<'_> {
    fn span(&self, name: &str) -> Option<&FieldSpan> {
        self.spans.iter().find(|s| s.name == name)
    }

    /// Every row's `gravity_body` values, unscaled, have norm 1 (when the field
    /// is there and its scales let it through the clip).
    fn gravity_is_unit(&self, path: &str, rows: &[f32]) -> Result<()> {
        let Some(g) = self.span("gravity_body") else {
            return Ok(());
        };
        if !rows.len().is_multiple_of(self.width) {
            return Ok(()); // not the fields' width: refused when the network runs
        }
        if g.scale.iter().any(|&s| s <= 0.0 || s > self.clip) {
            return Ok(());
        }
        for (r, row) in rows.chunks_exact(self.width).enumerate() {
            let norm = (0..3)
                .map(|i| (row[g.at + i] as f64 / g.scale[i]).powi(2))
                .sum::<f64>()
                .sqrt();
            ensure!(
                (norm - 1.0).abs() <= 1e-3,
                "sidecar `{path}[{r}]`: the values at `observation.fields[{}]` (gravity_body) have norm {norm:.4}, where gravity has norm 1: the fields are not listed in the order the network reads them",
                g.index
            );
        }
        Ok(())
    }

    /// `trace`'s rows, when the sidecar has them: gravity of norm 1, and each
    /// row's previous action, command, base velocity and joint angles equal to
    /// what the trace's own actions and states give.
    fn trace_follows_fields(&self, env: &EnvConfig) -> Result<()> {
        let Some(trace) = self.side.get("trace") else {
            return Ok(());
        };
        if trace.get("obs").is_none() {
            return Ok(());
        }
        let (obs, widths) = any_rows(self.side, "trace.obs")?;
        if !all_of_width(&widths, self.width) {
            return Ok(()); // not the fields' width: refused when the network runs
        }
        let n = widths.len();
        self.gravity_is_unit("trace.obs", &obs)?;
        let optional = |key: &str, width: usize| -> Result<Option<Vec<f32>>> {
            match trace.get(key) {
                Some(_) => rows(self.side, &format!("trace.{key}"), width).map(|r| Some(r.0)),
                None => Ok(None),
            }
        };
        let actions = optional("actions", ACT_DIM)?;
        let joint_pos = optional("joint_pos_rad", NUM_JOINTS)?;
        let base_vel = optional("base_lin_vel_body_mps", 3)?;
        let command = match trace.get("conditions").and_then(|c| c.get("command")) {
            Some(c) => Some(nums(c, "trace.conditions.command")?),
            None => None,
        };
        let defaults = nums(
            at(self.side, "joints.default_angles_rad_in_order")?,
            "joints.default_angles_rad_in_order",
        )?;
        for k in 0..n {
            let row = &obs[k * self.width..(k + 1) * self.width];
            let before = |v: &Option<Vec<f32>>, w: usize| -> Option<Vec<f64>> {
                let v = v.as_ref()?;
                let k = k.checked_sub(1)?;
                Some(v[k * w..(k + 1) * w].iter().map(|&x| x as f64).collect())
            };
            let previous = match k {
                0 => Some(vec![0.0; ACT_DIM]),
                _ => before(&actions, ACT_DIM),
            };
            let angles = before(&joint_pos, NUM_JOINTS)
                .map(|q| q.iter().zip(&defaults).map(|(q, d)| q - d).collect());
            let planar_moving = command
                .as_ref()
                .is_some_and(|c| c.len() == 3 && c[0].hypot(c[1]) >= env.commands.zero_below_mps);
            let expected = [
                ("previous_action", previous),
                (
                    "command_vx_vy_yaw",
                    command.clone().filter(|_| planar_moving),
                ),
                ("base_lin_vel_body", before(&base_vel, 3)),
                ("joint_pos_minus_default", angles),
            ];
            for (name, want) in expected {
                if let (Some(span), Some(want)) = (self.span(name), want) {
                    self.field_matches(k, row, span, &want)?;
                }
            }
        }
        Ok(())
    }

    /// Row `k` of `trace.obs` holds `physical x scale` (clipped) in `span`.
    fn field_matches(
        &self,
        k: usize,
        row: &[f32],
        span: &FieldSpan,
        physical: &[f64],
    ) -> Result<()> {
        for (i, (&p, &s)) in physical.iter().zip(&span.scale).enumerate() {
            let want = (p * s).clamp(-self.clip, self.clip);
            let got = row[span.at + i] as f64;
            ensure!(
                close(got, want),
                "sidecar `trace.obs[{k}]`: `observation.fields[{}]` ({}) holds {got} as its value {i}, but the trace's own actions and states give {want:.6}: the fields are not listed in the order the network reads them (or their scales are off)",
                span.index,
                span.name
            );
        }
        Ok(())
    }
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

/// Scales, clip and noise per field; the columns of rall's row the input takes,
/// and where each field sits in the input.
fn read_observation(
    side: &Value,
    env: &mut EnvConfig,
    joints: &[usize],
) -> Result<(Vec<usize>, Vec<FieldSpan>)> {
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
    let mut spans = Vec::with_capacity(fields.len());
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
        spans.push(FieldSpan {
            index: k,
            name: name.to_string(),
            at: columns.len(),
            scale: scale.clone(),
        });
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
    Ok((columns, spans))
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_misspelt_key_finds_the_key_meant() {
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        assert_eq!(edit_distance("", "abc"), 3);
        let field = SECTION_KEYS[2].1;
        let pd = SECTION_KEYS[5].1;
        let root = SECTION_KEYS[0].1;
        assert_eq!(
            nearest_key("training_noise_std", field),
            "training_noise_std_physical_units"
        );
        assert_eq!(nearest_key("kp", pd), "kp_nm_per_rad");
        assert_eq!(nearest_key("training_envelop", root), "training_envelope");
        assert_eq!(nearest_key("refrence", root), "reference");
    }
}
