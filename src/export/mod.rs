//! `rall export`: a checkpoint's policy as a standard ONNX model plus a JSON
//! sidecar with everything a robot controller needs (observation layout and
//! definitions, joint order and default pose, action law, PD gains, limits,
//! rates) and reference observation/action pairs to check any runtime against.
//!
//! ONNX is written through the ONNX protobuf schema hand-declared as `prost`
//! messages ([`onnx`]); no protoc, no new crate (prost 0.14.4 is rerun's).
//!
//! Network kinds: every exportable policy is a [`PolicyNet`] variant with its own
//! graph builder, inputs and sidecar description: the Gaussian actor's mean
//! (input `obs`), and RMA's student (inputs `obs` and `history`, the adaptation
//! module and the base policy in one graph). An RMA teacher is refused: it reads
//! privileged values a robot cannot measure.
//!
//! Safety ([`export_checked`], what `rall export` runs): the exported network's
//! command map goes into the sidecar as its safe envelope ([`envelope`]), and a
//! policy whose nominal trace falls or whose map fails inside its declared
//! command ranges is refused before anything is written, unless allowed.

pub mod deploy;
pub mod envelope;
pub mod onnx;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, ensure, Context, Result};
use serde_json::{json, Value};

use crate::config::TrainConfig;
use crate::env::observation::OBS_LAYOUT;
use crate::env::{build_scene, Env, EnvConfig, Scene, ACT_DIM, OBS_DIM};
use crate::eval::rall_graph::RallGraph;
use crate::eval::Actor;
use crate::learn::normalizer::STD_EPS;
use crate::learn::Learner;
use crate::robot::Robot;
use crate::runner::{load_policy, Progress};
use envelope::{Envelope, EnvelopeOptions};
use onnx::{Dense, Dim};

/// Version of the sidecar's JSON layout.
pub const SIDECAR_VERSION: u32 = 2;
/// Name of the observation input in every exported graph.
pub const OBS_INPUT: &str = "obs";
/// Name of the normalised observation inside a graph with a normaliser.
pub const NORMALIZED_OBS: &str = "obs_normalized";
/// Name of the history input of a student's graph.
pub const HISTORY_INPUT: &str = "history";
/// Name of the action output.
pub const ACTION_OUTPUT: &str = "actions";
/// Tolerance the test suite and `.ci` hold runtimes to on the reference pairs.
pub const REFERENCE_TOLERANCE: f64 = 1e-5;

/// What `rall export` does besides the checkpoint and output paths.
#[derive(Debug, Clone)]
pub struct ExportOptions {
    /// Reference observation/action pairs to write (taken along a rollout).
    pub reference_count: usize,
    /// Seed of the reference rollout (commands, friction, mass).
    pub seed: u64,
}

impl Default for ExportOptions {
    fn default() -> Self {
        ExportOptions {
            reference_count: 8,
            seed: 0,
        }
    }
}

/// What was written.
#[derive(Debug, Clone)]
pub struct ExportReport {
    pub onnx_path: PathBuf,
    pub sidecar_path: PathBuf,
    pub iteration: usize,
    pub config_hash: String,
    pub onnx_bytes: usize,
    pub reference_count: usize,
    /// The command envelope of a checked export ([`export_checked`]).
    pub envelope: Option<EnvelopeReport>,
}

/// The learner's empirical observation normaliser (`learner.obs_normalization`),
/// written as the graph's first two nodes `(obs - mean) * inv_std`: the same f32
/// operations the checkpoint applies, so the graph computes what the checkpoint
/// computes. (Folding it into the first layer would round differently.)
#[derive(Debug, Clone, PartialEq)]
pub struct ObsNormalizer {
    pub mean: Vec<f32>,
    /// `1 / (sqrt(var) + STD_EPS)`, as the learner computes it from its variance.
    pub inv_std: Vec<f32>,
}

impl ObsNormalizer {
    /// The normaliser of `learner`, if it has one.
    pub fn of_learner(learner: &Learner) -> Option<ObsNormalizer> {
        let n = learner.obs_normalizer()?;
        let state = n.state();
        let var = &state.iter().find(|t| t.name == "obs_norm.var")?.data;
        Some(ObsNormalizer {
            mean: n.mean().to_vec(),
            inv_std: var.iter().map(|v| 1.0 / (v.sqrt() + STD_EPS)).collect(),
        })
    }

    /// `(x - mean) * inv_std` in f64 (the reference forward pass).
    fn apply_f64(&self, x: &[f64]) -> Vec<f64> {
        x.iter()
            .zip(self.mean.iter().zip(&self.inv_std))
            .map(|(v, (&m, &s))| (v - m as f64) * s as f64)
            .collect()
    }
}

/// An exportable policy network. One variant per network kind, each with its
/// own graph inputs and sidecar description.
#[derive(Debug, Clone)]
pub enum PolicyNet {
    /// The Gaussian actor's mean: `actions = MLP(obs)`, ELU between layers, the
    /// observation normalised first when the learner has a normaliser.
    GaussianMean {
        norm: Option<ObsNormalizer>,
        layers: Vec<Dense>,
    },
    /// RMA's student: `z = adaptation(history)`, `actions = base([obs, z])`.
    Student {
        adaptation: Vec<Dense>,
        base: Vec<Dense>,
        obs_dim: usize,
        history_steps: usize,
    },
}

/// Dense layers `{prefix}l0`, `{prefix}l1`, ... of the actor's parameters.
fn dense_layers(learner: &Learner, prefix: &str) -> Result<Vec<Dense>> {
    let ps = &learner.actor_critic().actor.params;
    let find = |name: &str| ps.entries.iter().find(|e| e.name == name);
    let mut layers: Vec<Dense> = Vec::new();
    while let Some(w) = find(&format!("{prefix}l{}.weight", layers.len())) {
        let i = layers.len();
        let b = find(&format!("{prefix}l{i}.bias"))
            .with_context(|| format!("actor.{prefix}l{i} has a weight but no bias"))?;
        ensure!(
            w.shape.len() == 2 && b.shape == [w.shape[1]],
            "actor.{prefix}l{i}: weight {:?} and bias {:?} do not form a dense layer",
            w.shape,
            b.shape
        );
        if let Some(prev) = layers.last() {
            ensure!(
                prev.out == w.shape[0],
                "actor.{prefix}l{} has {} outputs but actor.{prefix}l{i} takes {} inputs",
                i - 1,
                prev.out,
                w.shape[0]
            );
        }
        layers.push(Dense {
            inp: w.shape[0],
            out: w.shape[1],
            weight: ps.data[w.offset..w.offset + w.len()].to_vec(),
            bias: ps.data[b.offset..b.offset + b.len()].to_vec(),
        });
    }
    ensure!(
        !layers.is_empty(),
        "the actor has no layers actor.{prefix}l0"
    );
    Ok(layers)
}

/// Reference forward pass of dense layers in f64, ELU between them.
fn mlp_f64(layers: &[Dense], input: &[f64]) -> Vec<f64> {
    let mut x = input.to_vec();
    for (i, l) in layers.iter().enumerate() {
        let mut y: Vec<f64> = l.bias.iter().map(|&b| b as f64).collect();
        for (k, xv) in x.iter().enumerate() {
            for (j, yv) in y.iter_mut().enumerate() {
                *yv += xv * l.weight[k * l.out + j] as f64;
            }
        }
        if i + 1 < layers.len() {
            for v in &mut y {
                if *v <= 0.0 {
                    *v = v.exp_m1();
                }
            }
        }
        x = y;
    }
    x
}

impl PolicyNet {
    /// The deployable network of a learner (its actor's mean, normalised by `norm`).
    pub fn from_learner(learner: &Learner, norm: Option<&ObsNormalizer>) -> Result<PolicyNet> {
        let actor = &learner.actor_critic().actor;
        if learner.latent_source() == crate::learn::LatentSource::Adaptation {
            let adaptation = dense_layers(learner, "adapt.")?;
            let base = dense_layers(learner, "")?;
            let obs_dim = actor.direct_input().width();
            let latent = actor.latent_dim();
            let hist = adaptation[0].inp;
            ensure!(
                norm.is_none(),
                "a student's observation normaliser cannot be exported yet"
            );
            ensure!(
                base[0].inp == obs_dim + latent
                    && adaptation[adaptation.len() - 1].out == latent
                    && hist % obs_dim == 0,
                "student shapes do not fit: base takes {}, obs {obs_dim} + latent {latent}; adaptation {hist} -> {}",
                base[0].inp,
                adaptation[adaptation.len() - 1].out
            );
            return Ok(PolicyNet::Student {
                adaptation,
                base,
                obs_dim,
                history_steps: hist / obs_dim,
            });
        }
        let layers = dense_layers(learner, "")?;
        let (inp, out) = (layers[0].inp, layers[layers.len() - 1].out);
        ensure!(
            inp == actor.obs_dim && out == actor.act_dim,
            "actor maps {inp} -> {out}, expected {} -> {}",
            actor.obs_dim,
            actor.act_dim
        );
        if let Some(n) = norm {
            ensure!(
                n.mean.len() == inp && n.inv_std.len() == inp,
                "normaliser of size {} does not fit an actor with {inp} inputs",
                n.mean.len()
            );
        }
        Ok(PolicyNet::GaussianMean {
            norm: norm.cloned(),
            layers,
        })
    }

    pub fn kind(&self) -> &'static str {
        match self {
            PolicyNet::GaussianMean { .. } => "gaussian_actor_mean",
            PolicyNet::Student { .. } => "rma_student",
        }
    }

    /// Graph inputs: (name, shape).
    pub fn inputs(&self) -> Vec<(&'static str, Vec<Dim>)> {
        match self {
            PolicyNet::GaussianMean { layers, .. } => vec![(
                OBS_INPUT,
                vec![
                    Dim::Named(onnx::BATCH_DIM.into()),
                    Dim::Fixed(layers[0].inp),
                ],
            )],
            PolicyNet::Student {
                obs_dim,
                history_steps,
                ..
            } => vec![
                (
                    OBS_INPUT,
                    vec![Dim::Named(onnx::BATCH_DIM.into()), Dim::Fixed(*obs_dim)],
                ),
                (
                    HISTORY_INPUT,
                    vec![
                        Dim::Named(onnx::BATCH_DIM.into()),
                        Dim::Fixed(history_steps * obs_dim),
                    ],
                ),
            ],
        }
    }

    pub fn act_dim(&self) -> usize {
        match self {
            PolicyNet::GaussianMean { layers, .. } => layers[layers.len() - 1].out,
            PolicyNet::Student { base, .. } => base[base.len() - 1].out,
        }
    }

    /// The ONNX graph.
    pub fn graph(&self) -> onnx::GraphProto {
        let mut g = onnx::GraphProto {
            name: format!("rall_{}", self.kind()),
            ..Default::default()
        };
        for (name, dims) in self.inputs() {
            let doc = if name == HISTORY_INPUT {
                "the last policy observations, newest first, see the JSON sidecar"
            } else {
                "policy observation, see the JSON sidecar"
            };
            g.input.push(onnx::float_value_info(name, &dims, doc));
        }
        match self {
            PolicyNet::GaussianMean { norm, layers } => {
                let mut x = OBS_INPUT;
                if let Some(n) = norm {
                    onnx::push_normalizer(&mut g, &n.mean, &n.inv_std, x, NORMALIZED_OBS);
                    x = NORMALIZED_OBS;
                }
                onnx::push_mlp(&mut g, "actor.", layers, x, ACTION_OUTPUT);
            }
            PolicyNet::Student {
                adaptation, base, ..
            } => {
                onnx::push_mlp(&mut g, "actor.adapt.", adaptation, HISTORY_INPUT, "latent");
                onnx::push_concat(
                    &mut g,
                    "obs_latent",
                    &[OBS_INPUT, "latent"],
                    1,
                    "base_input",
                );
                onnx::push_mlp(&mut g, "actor.", base, "base_input", ACTION_OUTPUT);
            }
        }
        g.output.push(onnx::float_value_info(
            ACTION_OUTPUT,
            &[
                Dim::Named(onnx::BATCH_DIM.into()),
                Dim::Fixed(self.act_dim()),
            ],
            "raw action (before clip and scale); feed it back as previous_action",
        ));
        g
    }

    /// The checkpoint tensors this network came from, and how it computes.
    fn describe(&self) -> Value {
        match self {
            PolicyNet::Student {
                adaptation,
                base,
                obs_dim,
                history_steps,
            } => {
                let tensors = |prefix: &str, layers: &[Dense]| -> Vec<Value> {
                    layers
                        .iter()
                        .enumerate()
                        .flat_map(|(i, l)| {
                            [
                                json!({"name": format!("actor.{prefix}l{i}.weight"), "shape": [l.inp, l.out],
                                       "layout": "in x out, row-major (y = x W + b)"}),
                                json!({"name": format!("actor.{prefix}l{i}.bias"), "shape": [l.out]}),
                            ]
                        })
                        .collect()
                };
                let all_tensors = [tensors("adapt.", adaptation), tensors("", base)].concat();
                json!({
                    "kind": self.kind(),
                    "formula": "z = MLP_adapt(history); actions = MLP_base([obs, z]) (obs first, then the latent)",
                    "activation": "ELU with alpha 1 between layers of each MLP, none after their last",
                    "history": format!("{history_steps} policy observations of {obs_dim} values, newest first: slot 0 is this step's obs, slot k the obs k steps ago; zeros for steps before the episode's first"),
                    "latent_dim": adaptation[adaptation.len() - 1].out,
                    "checkpoint_tensors": all_tensors,
                    "not_exported": "actor.enc.* (the teacher's encoder of privileged information), actor.log_std, critic.*, adam.*, adapt_adam.*, lr",
                    "onnx_ops": "Gemm (transB = 0), Elu (alpha 1), Concat (axis 1)",
                })
            }
            PolicyNet::GaussianMean { norm, layers } => {
                let tensors: Vec<Value> = layers
                    .iter()
                    .enumerate()
                    .flat_map(|(i, l)| {
                        [
                            json!({"name": format!("actor.l{i}.weight"), "shape": [l.inp, l.out],
                                   "layout": "in x out, row-major (y = x W + b)"}),
                            json!({"name": format!("actor.l{i}.bias"), "shape": [l.out]}),
                        ]
                    })
                    .collect();
                let n = layers.len();
                let h0 = if norm.is_some() {
                    "(obs - obs_norm.mean) * obs_norm.inv_std"
                } else {
                    "obs"
                };
                json!({
                    "kind": self.kind(),
                    "formula": format!(
                        "h_0 = {h0}; h_(i+1) = elu(h_i W_i + b_i) for i < {last}; actions = h_{last} W_{last} + b_{last}",
                        last = n - 1
                    ),
                    "activation": "ELU with alpha 1 (elu(x) = x if x > 0 else exp(x) - 1) between layers, none after the last",
                    "layer_sizes": std::iter::once(layers[0].inp).chain(layers.iter().map(|l| l.out)).collect::<Vec<_>>(),
                    "checkpoint_tensors": tensors,
                    "not_exported": "actor.log_std (the Gaussian's log standard deviation; deployment uses the mean), critic.*, adam.*, lr",
                    "onnx_ops": "Sub and Mul for the normaliser (when there is one), Gemm (transB = 0, so W is used as stored) and Elu (alpha 1); initializers named like the checkpoint tensors",
                })
            }
        }
    }

    /// The sidecar's `onnx.normalizer`.
    fn normalizer_json(&self) -> Value {
        match self {
            PolicyNet::GaussianMean { norm: Some(_), .. } => json!({
                "kind": "in_graph",
                "formula": "(obs - obs_norm.mean) * obs_norm.inv_std, the graph's first nodes (Sub, Mul), with inv_std = 1 / (sqrt(obs_norm.var) + 0.01) from the checkpoint",
                "note": "the graph's input is the scaled observation below; the normaliser is part of the network, not of the observation builder",
            }),
            _ => json!({
                "kind": "identity",
                "note": "the policy was trained without an observation normaliser: the network takes the scaled observation below as is",
            }),
        }
    }

    /// Reference forward pass in f64 of one input row per graph input (in
    /// [`Self::inputs`] order).
    pub fn forward_inputs_f64(&self, inputs: &[&[f32]]) -> Vec<f64> {
        let f = |x: &[f32]| x.iter().map(|&v| v as f64).collect::<Vec<f64>>();
        match self {
            PolicyNet::GaussianMean { .. } => self.forward_f64(inputs[0]),
            PolicyNet::Student {
                adaptation, base, ..
            } => {
                let z = mlp_f64(adaptation, &f(inputs[1]));
                let mut x = f(inputs[0]);
                x.extend(z);
                mlp_f64(base, &x)
            }
        }
    }

    /// Reference forward pass in f64 (what the ONNX graph computes) of one row:
    /// the graph's inputs concatenated in [`Self::inputs`] order.
    pub fn forward_f64(&self, obs: &[f32]) -> Vec<f64> {
        match self {
            PolicyNet::Student { obs_dim, .. } => {
                let (o, h) = obs.split_at((*obs_dim).min(obs.len()));
                self.forward_inputs_f64(&[o, h])
            }
            PolicyNet::GaussianMean { norm, layers } => {
                let x: Vec<f64> = obs.iter().map(|&v| v as f64).collect();
                match norm {
                    Some(n) => mlp_f64(layers, &n.apply_f64(&x)),
                    None => mlp_f64(layers, &x),
                }
            }
        }
    }
}

/// FNV-1a (64 bit) of `text`, as 16 hex digits.
pub fn fnv1a64_hex(text: &str) -> String {
    format!("{:016x}", crate::hash::fnv1a64(text.bytes()))
}

/// The sidecar path beside an ONNX path: `OUT.onnx` -> `OUT.json`.
pub fn sidecar_path(onnx_path: &Path) -> PathBuf {
    onnx_path.with_extension("json")
}

/// Noise-free definition of each observation field (by `OBS_LAYOUT` name).
fn field_definition(name: &str) -> Option<(&'static str, &'static str)> {
    Some(match name {
        "base_lin_vel_body" => ("m/s", "linear velocity of the trunk frame origin (the trunk box centre = site `imu` in mjcf/aliengo.xml, NOT the centre of mass), expressed in the trunk (body) frame: x forward, y left, z up. In MuJoCo: R(quat)^T qvel[0:3] of the free joint. A world-frame velocity here makes the robot fall."),
        "base_ang_vel_body" => ("rad/s", "angular velocity of the trunk in the trunk (body) frame (x roll rate, y pitch rate, z yaw rate), i.e. the IMU gyroscope. In MuJoCo: qvel[3:6] of the free joint."),
        "gravity_body" => ("unit vector (dimensionless)", "direction of gravity in the trunk frame, a UNIT vector: (0, 0, -1) when the trunk is level, R(quat)^T (0, 0, -1). Not m/s^2: an accelerometer reading must be normalised (and negated: an accelerometer at rest reads +g up)."),
        "command_vx_vy_yaw" => ("m/s, m/s, rad/s", "the velocity command: forward and lateral speed in the trunk frame (compared with base_lin_vel_body x, y) and yaw rate (compared with base_ang_vel_body z). Planar commands of norm below commands.zero_below_mps were zeroed in training."),
        "joint_pos_minus_default" => ("rad", "joint angle minus that joint's default angle, joints in `joints.names` order (FR, FL, RR, RL x hip, thigh, calf), angles in the MJCF/Unitree convention (same zero and sign)."),
        "joint_vel" => ("rad/s", "joint velocity, joints in `joints.names` order."),
        "previous_action" => ("raw network output", "the `actions` output of the previous policy step exactly as the network returned it: BEFORE the clip and BEFORE the action scale (not the target angle, not the scaled offset). Zeros at the first step of an episode."),
        _ => return None,
    })
}

/// Observation fields with offsets, scales and definitions, from the env config.
fn observation_json(env: &EnvConfig) -> Result<Value> {
    let o = &env.observation;
    let mut offset = 0;
    let mut fields = Vec::new();
    for (name, len) in OBS_LAYOUT {
        let (scale, noise): (Vec<f64>, f64) = match name {
            "base_lin_vel_body" => (vec![o.scales.lin_vel; 3], o.noise_std.lin_vel),
            "base_ang_vel_body" => (vec![o.scales.ang_vel; 3], o.noise_std.ang_vel),
            "gravity_body" => (vec![o.scales.gravity; 3], o.noise_std.gravity),
            "command_vx_vy_yaw" => (o.command_scale.to_vec(), 0.0),
            "joint_pos_minus_default" => (vec![o.scales.dof_pos; len], o.noise_std.dof_pos),
            "joint_vel" => (vec![o.scales.dof_vel; len], o.noise_std.dof_vel),
            "previous_action" => (vec![1.0; len], 0.0),
            _ => bail!("observation field `{name}` has no scale in the exporter"),
        };
        let (units, definition) = field_definition(name).with_context(|| {
            format!("observation field `{name}` has no definition in the exporter")
        })?;
        fields.push(json!({
            "name": name,
            "offset": offset,
            "length": len,
            "scale": scale,
            "units": units,
            "definition": definition,
            "training_noise_std_physical_units": noise * o.noise_level,
            "noise_std_physical_units": noise,
        }));
        offset += len;
    }
    ensure!(
        offset == OBS_DIM,
        "observation layout sums to {offset}, expected {OBS_DIM}"
    );
    Ok(json!({
        "dim": OBS_DIM,
        "order": OBS_LAYOUT.iter().map(|(n, _)| *n).collect::<Vec<_>>(),
        "formula": format!("obs[offset + k] = clip(value[k] * scale[k], -{c}, {c}) as float32, fields concatenated in `order`", c = o.clip),
        "clip": o.clip,
        "noise_level": o.noise_level,
        "fields": fields,
        "noise": "rall adds Gaussian noise (training_noise_std_physical_units * scale) during training and `rall eval`; on the robot feed the noise-free values, the sensors add their own",
    }))
}

/// Reference pairs from a rollout of the policy's mean on flat ground (noise off).
fn reference_pairs(
    learner: &Learner,
    env_cfg: &EnvConfig,
    count: usize,
    seed: u64,
) -> Result<Vec<f32>> {
    let mut cfg = crate::eval::tracking::tracking_env(env_cfg);
    cfg.observation.noise_level = 0.0;
    let scene = build_scene(&cfg, seed)?;
    let mut env = Env::new(Arc::new(cfg), &scene.model, None, seed, 0)?;
    let mut obs = vec![0.0f32; env.obs_width()];
    let mut final_obs = vec![0.0f32; env.obs_width()];
    env.reset(&mut obs)?;
    let every = 10;
    let mut out = Vec::with_capacity(count * OBS_DIM);
    for step in 0..count * every {
        if step % every == 0 {
            out.extend_from_slice(&obs);
        }
        let action = learner.act_mean(&obs);
        if env.step(&action, &mut obs, &mut final_obs).done {
            env.reset(&mut obs)?;
        }
    }
    Ok(out)
}

/// Writes `onnx_path` and its sidecar (`.json` beside it) for the checkpoint at
/// `checkpoint`, without the safety checks of [`export_checked`] (the sidecar's
/// `safety.checked` says so; it has no `command_envelope`).
pub fn export(checkpoint: &Path, onnx_path: &Path, opts: &ExportOptions) -> Result<ExportReport> {
    check_export_paths(onnx_path, opts)?;
    let loaded = load_policy(checkpoint)?;
    export_learner(
        &loaded.learner,
        &loaded.config,
        &loaded.progress,
        checkpoint,
        onnx_path,
        opts,
    )
}

/// What `rall export` does: [`export`] after mapping the exported network's
/// command envelope; refuses an unsafe policy (writing nothing) unless
/// `safety.allow_unsafe`.
pub fn export_checked(
    checkpoint: &Path,
    onnx_path: &Path,
    opts: &ExportOptions,
    safety: &SafetyCheck,
) -> Result<ExportReport> {
    check_export_paths(onnx_path, opts)?;
    let loaded = load_policy(checkpoint)?;
    export_learner_checked(
        &loaded.learner,
        &loaded.config,
        &loaded.progress,
        checkpoint,
        onnx_path,
        opts,
        safety,
    )
}

/// The output must be an `.onnx` path and at least one reference pair asked for.
fn check_export_paths(onnx_path: &Path, opts: &ExportOptions) -> Result<()> {
    ensure!(
        onnx_path.extension().is_some_and(|e| e == "onnx"),
        "--onnx {}: the output must end in .onnx (the sidecar goes beside it as .json)",
        onnx_path.display()
    );
    ensure!(
        opts.reference_count > 0,
        "at least one reference observation is needed"
    );
    Ok(())
}

/// [`export`] from an already loaded learner.
pub fn export_learner(
    learner: &Learner,
    config: &TrainConfig,
    progress: &Progress,
    checkpoint: &Path,
    onnx_path: &Path,
    opts: &ExportOptions,
) -> Result<ExportReport> {
    let mut built = build_export(learner, config, progress, checkpoint, onnx_path, opts)?;
    if let Some(step) = built.trace_fell_at_step {
        eprintln!("note: the nominal trace stops at step {step}: the policy fell walking at {:?} on flat ground", deploy::TRACE_COMMAND);
    }
    built.sidecar["safety"] = envelope::unchecked_json(built.trace_fell_at_step);
    built.write(None)
}

/// [`export_checked`] from an already loaded learner.
pub fn export_learner_checked(
    learner: &Learner,
    config: &TrainConfig,
    progress: &Progress,
    checkpoint: &Path,
    onnx_path: &Path,
    opts: &ExportOptions,
    safety: &SafetyCheck,
) -> Result<ExportReport> {
    safety.envelope.validate(&config.env.commands)?;
    let mut built = build_export(learner, config, progress, checkpoint, onnx_path, opts)?;
    let fell = built.trace_fell_at_step;
    if let (Some(step), false) = (fell, safety.allow_unsafe) {
        return Err(envelope::trace_refusal(checkpoint, step));
    }
    let graph = match &built.net {
        PolicyNet::GaussianMean { .. } => Some(ExportedGraph::read(&built.bytes, config)?),
        PolicyNet::Student { .. } => None,
    };
    let (actor, network): (&(dyn Actor + Sync), &str) = match &graph {
        Some(g) => (g, "the exported ONNX graph, read back from its bytes and run by rall's actor forward (the actions any runtime reproduces to reference.tolerance_abs)"),
        None => (learner, "the checkpoint's actor: an RMA student's two-input graph computes the same actions (reference); rall runs it in its checkpoint form"),
    };
    eprintln!(
        "mapping the command envelope: {} robots per cell, flat ground, seed {} ...",
        safety.envelope.robots, safety.envelope.seed
    );
    let measured = Envelope::measure(actor, &config.env, &safety.envelope, network)?;
    eprintln!(
        "{}\n\n{}",
        measured.map.summary(&measured.threshold),
        measured.map.table(&measured.threshold)
    );
    let verdict = envelope::judge(checkpoint, fell, &measured, safety.allow_unsafe)?;
    built.sidecar["command_envelope"] = measured.json(checkpoint);
    built.sidecar["safety"] = verdict;
    built.write(Some(EnvelopeReport::of(
        &measured,
        fell,
        safety.allow_unsafe,
    )))
}

/// How `rall export` checks a policy before writing it.
#[derive(Debug, Clone, Default)]
pub struct SafetyCheck {
    pub envelope: EnvelopeOptions,
    /// Write an unsafe policy anyway (its sidecar says so).
    pub allow_unsafe: bool,
}

/// What a checked export found.
#[derive(Debug, Clone)]
pub struct EnvelopeReport {
    pub cells: usize,
    pub safe_cells: usize,
    /// Failing cells inside the declared command ranges.
    pub declared_failures: usize,
    pub trace_fell_at_step: Option<usize>,
    /// An unsafe policy written because `--allow-unsafe` was given.
    pub allowed_unsafe: bool,
}

impl EnvelopeReport {
    fn of(env: &Envelope, fell: Option<usize>, allow_unsafe: bool) -> EnvelopeReport {
        let t = &env.threshold;
        let declared_failures = env.declared_failures().len();
        EnvelopeReport {
            cells: env.map.cells.len(),
            safe_cells: env.map.safe_cells(t).len(),
            declared_failures,
            trace_fell_at_step: fell,
            allowed_unsafe: allow_unsafe && (fell.is_some() || declared_failures > 0),
        }
    }
}

/// The exported graph as an actor: rall's reading of the ONNX bytes just
/// encoded, run by rall's actor forward.
struct ExportedGraph(RallGraph);

impl ExportedGraph {
    /// Reads `bytes` back; refuses a graph rall cannot read or whose input is not
    /// the env's observation row.
    fn read(bytes: &[u8], config: &TrainConfig) -> Result<ExportedGraph> {
        let g = RallGraph::recognise(bytes)
            .context("the exported graph does not read back as rall's export form")?;
        let width = config.env.obs_layout().width();
        ensure!(
            g.input_width() == width,
            "the exported graph takes {} inputs, the observation row has {width}",
            g.input_width()
        );
        Ok(ExportedGraph(g))
    }
}

impl Actor for ExportedGraph {
    fn actions(&self, obs: &[f32]) -> Result<Vec<f32>> {
        let w = self.0.input_width();
        ensure!(
            obs.len().is_multiple_of(w),
            "observation rows of {w} expected, got {} values",
            obs.len()
        );
        Ok(self.0.actions(obs, obs.len() / w))
    }
}

/// An export built in memory, not yet written.
struct BuiltExport {
    net: PolicyNet,
    sidecar: Value,
    bytes: Vec<u8>,
    onnx_path: PathBuf,
    iteration: usize,
    config_hash: String,
    reference_count: usize,
    /// Where the nominal trace fell (None: it did not, or a student has none).
    trace_fell_at_step: Option<usize>,
}

impl BuiltExport {
    /// Writes the ONNX file and its sidecar.
    fn write(self, envelope: Option<EnvelopeReport>) -> Result<ExportReport> {
        let side = write_export_files(&self.onnx_path, &self.bytes, &self.sidecar)?;
        Ok(ExportReport {
            onnx_path: self.onnx_path,
            sidecar_path: side,
            iteration: self.iteration,
            config_hash: self.config_hash,
            onnx_bytes: self.bytes.len(),
            reference_count: self.reference_count,
            envelope,
        })
    }
}

/// The graph and sidecar of `learner`, with its nominal trace, in memory.
fn build_export(
    learner: &Learner,
    config: &TrainConfig,
    progress: &Progress,
    checkpoint: &Path,
    onnx_path: &Path,
    opts: &ExportOptions,
) -> Result<BuiltExport> {
    let env = &config.env;
    let groups = env.obs_layout();
    let student = learner.latent_source() == crate::learn::LatentSource::Adaptation;
    check_deployable(student, config, checkpoint)?;
    let norm = ObsNormalizer::of_learner(learner);
    let net = PolicyNet::from_learner(learner, norm.as_ref())?;
    ensure!(
        net.act_dim() == ACT_DIM,
        "policy outputs {} actions, the robot has {ACT_DIM}",
        net.act_dim()
    );
    let config_hash = fnv1a64_hex(&config.to_toml());
    let reference = Reference::new(learner, config, opts)?;
    let source = SidecarSource {
        net: &net,
        progress,
        checkpoint,
        onnx_path,
        config_hash: &config_hash,
    };
    let scene = build_scene(env, config.runner.seed)?;
    let robot = Robot::new(scene.model.try_clone()?, env.control.clone())?;
    let mut sidecar = sidecar_json(&source, config, &robot, &reference)?;
    if let PolicyNet::Student { history_steps, .. } = &net {
        add_history_json(&mut sidecar, *history_steps, &reference.history);
    }
    let fell = add_deployment(&mut sidecar, learner, config, (&robot, &scene), student)?;
    let metadata = onnx_metadata(onnx_path, progress, &config_hash);
    let model = onnx::model(net.graph(), model_doc(student), &metadata);
    Ok(BuiltExport {
        bytes: onnx::encode(&model),
        net,
        sidecar,
        onnx_path: onnx_path.to_path_buf(),
        iteration: progress.iteration,
        config_hash,
        reference_count: reference.rows.len() / groups.width(),
        trace_fell_at_step: fell,
    })
}

/// Refuses a policy a robot cannot run: one reading privileged observations
/// (an RMA teacher), or a student that does not read `policy` and `history`.
fn check_deployable(student: bool, config: &TrainConfig, checkpoint: &Path) -> Result<()> {
    let groups = config.env.obs_layout();
    if student {
        ensure!(
            groups.range("history").is_some() && config.learner.actor_inputs == ["policy"],
            "{}: an RMA student must read `policy` directly and `history` through its adaptation module",
            checkpoint.display()
        );
    } else {
        ensure!(
            groups.names() == ["policy"] && config.learner.encoder.is_none(),
            "{}: the policy reads observation groups [{}]{}: a robot cannot measure the privileged ones (an RMA teacher); export its student, the checkpoint after phase 2",
            checkpoint.display(),
            groups.names().join(", "),
            if config.learner.encoder.is_some() { " and a latent of the privileged group" } else { "" }
        );
    }
    Ok(())
}

/// Reference observations along a rollout of the policy, with its actions for them.
struct Reference {
    /// Full observation rows (every group).
    rows: Vec<f32>,
    actions: Vec<f32>,
    /// The graph's inputs: the policy group, and a student's history.
    obs: Vec<f32>,
    history: Vec<f32>,
}

impl Reference {
    fn new(learner: &Learner, config: &TrainConfig, opts: &ExportOptions) -> Result<Reference> {
        let groups = config.env.obs_layout();
        let rows = reference_pairs(learner, &config.env, opts.reference_count, opts.seed)?;
        let actions = learner.act_mean(&rows);
        let pick = |name: &str| -> Vec<f32> {
            let mut out = Vec::new();
            if let Some(r) = groups.range(name) {
                crate::learn::gather_columns(&rows, groups.width(), &[r], &mut out);
            }
            out
        };
        let (obs, history) = (pick("policy"), pick("history"));
        Ok(Reference {
            rows,
            actions,
            obs,
            history,
        })
    }
}

/// Rows of `d` values.
fn json_rows(v: &[f32], d: usize) -> Vec<Vec<f32>> {
    v.chunks_exact(d).map(<[f32]>::to_vec).collect()
}

fn file_name(p: &Path) -> Option<String> {
    p.file_name().map(|f| f.to_string_lossy().into_owned())
}

/// What the sidecar says about where the policy came from and its graph.
struct SidecarSource<'a> {
    net: &'a PolicyNet,
    progress: &'a Progress,
    checkpoint: &'a Path,
    onnx_path: &'a Path,
    config_hash: &'a str,
}

/// The sidecar: the checkpoint, the graph, the observation, the robot's
/// joints, action, PD law and rates, the control loop, and the references.
fn sidecar_json(
    src: &SidecarSource,
    config: &TrainConfig,
    robot: &Robot,
    reference: &Reference,
) -> Result<Value> {
    let (net, progress) = (src.net, src.progress);
    let inputs: Vec<Value> = net
        .inputs()
        .iter()
        .map(|(n, dims)| json!({"name": n, "dtype": "float32", "shape": dims_json(dims)}))
        .collect();
    let mut sidecar = json!({
        "format": "rall-onnx-sidecar",
        "format_version": SIDECAR_VERSION,
        "onnx_file": file_name(src.onnx_path),
        "checkpoint": {
            "file": file_name(src.checkpoint),
            "iteration": progress.iteration,
            "total_env_steps": progress.total_env_steps,
            "config_hash": src.config_hash,
            "config_hash_algorithm": "FNV-1a 64-bit over the checkpoint's run config re-serialised as TOML (rall's TrainConfig::to_toml)",
            "rall_version": env!("CARGO_PKG_VERSION"),
        },
        "onnx": {
            "opset": onnx::OPSET,
            "ir_version": onnx::IR_VERSION,
            "inputs": inputs,
            "outputs": [{"name": ACTION_OUTPUT, "dtype": "float32", "shape": [onnx::BATCH_DIM, net.act_dim()],
                         "meaning": "raw action a (the Gaussian policy's mean): not clipped, not scaled"}],
            "batch_dimension": "dynamic (`batch`); a controller feeds batch 1",
            "normalizer": net.normalizer_json(),
        },
        "network": net.describe(),
        "observation": observation_json(&config.env)?,
        "deployment_check": "`trace` below is the check for a deployment loop (observation builder, network, action law, PD, rates): replay it as its `purpose` says; `reference` checks the network alone",
        "reference": {
            "description": format!("{} noise-free observations along a rollout of this policy on flat ground in rall (every 10th policy step), with the actions rall computes for them; a runtime feeding `observations` as one batch must return `actions` within the tolerance", reference.obs.len() / OBS_DIM),
            "tolerance_abs": REFERENCE_TOLERANCE,
            "observations": json_rows(&reference.obs, OBS_DIM),
            "actions": json_rows(&reference.actions, ACT_DIM),
        },
    });
    add_robot_json(&mut sidecar, config, robot)?;
    Ok(sidecar)
}

/// The sidecar's robot sections: joints, action, PD law, rates, control loop.
fn add_robot_json(sidecar: &mut Value, config: &TrainConfig, robot: &Robot) -> Result<()> {
    let env = &config.env;
    let names = robot.layout.joint_names.clone();
    let default_q = robot.default_q_rad;
    let c = &env.control;
    let by_name = |vals: &dyn Fn(usize) -> f64| -> serde_json::Map<String, Value> {
        names
            .iter()
            .enumerate()
            .map(|(i, n)| (n.clone(), json!(vals(i))))
            .collect()
    };
    sidecar["joints"] = json!({
        "names": &names,
        "order": "Unitree SDK: FR, FL, RR, RL legs x (hip, thigh, calf); index i of every per-joint array below and of the observation and action",
        "default_angles_rad": by_name(&|i| default_q[i]),
        "default_angles_rad_in_order": default_q.to_vec(),
        "source": format!("keyframe `{}` of {}", c.default_keyframe, env.robot_mjcf),
        "keyframe": c.default_keyframe,
        "mjcf_actuator_names": deploy::actuator_names(robot),
        "mjcf_actuators": "the MJCF `motor` driving joint i is mjcf_actuator_names[i] (the MJCF declares them in this same order); send torque i to it",
        "torque_limits_nm": by_name(&|i| c.torque_limit_nm(i)),
    });
    sidecar["action"] = json!({
        "dim": ACT_DIM,
        "clip": c.clip_actions,
        "scale_rad": c.action_scale_rad,
        "target_law": format!("q_target[i] = default_angles_rad[i] + {s} * clip(a[i], -{k}, {k})   (rad), held for one policy step", s = c.action_scale_rad, k = c.clip_actions),
        "previous_action": "observation field previous_action = the raw a returned at the previous policy step (before clip and scale)",
    });
    sidecar["pd"] = json!({
        "kp_nm_per_rad": c.kp_nm_per_rad,
        "kd_nm_s_per_rad": c.kd_nm_s_per_rad,
        "torque_limits_nm": by_name(&|i| c.torque_limit_nm(i)),
        "law": format!("every physics step (every {dt} s): tau[i] = clip({kp} * (q_target[i] - q[i]) - {kd} * qdot[i], -limit[i], limit[i]) with fresh q, qdot; desired joint velocity 0, no feed-forward torque", dt = c.physics_dt_s, kp = c.kp_nm_per_rad, kd = c.kd_nm_s_per_rad),
        "on_motor_drivers": "a driver that runs its own PD gets q_des = q_target, dq_des = 0, Kp, Kd as above, tau_ff = 0, and its torque limit set to torque_limits_nm",
    });
    sidecar["rates"] = json!({
        "physics_dt_s": c.physics_dt_s,
        "pd_rate_hz": 1.0 / c.physics_dt_s,
        "decimation": c.decimation,
        "policy_dt_s": c.policy_dt_s(),
        "policy_rate_hz": 1.0 / c.policy_dt_s(),
    });
    sidecar["control_loop"] = json!([
            format!("at {:.0} Hz: read the trunk state (body-frame linear and angular velocity, orientation) and the 12 joint angles and velocities", 1.0 / c.policy_dt_s()),
            "build obs (1 x 48) field by field as in `observation` (scale, then clip), with previous_action = the raw network output of the previous step (zeros at start)",
            "a = onnx(obs)[0]  (12 raw values); keep a for the next observation",
            "q_target = default_angles_rad + scale_rad * clip(a, -clip, clip)",
            format!("until the next policy step, every {} s: tau = clip(kp (q_target - q) - kd qdot, +-torque limit), sent to the motors in `joints.names` order", c.physics_dt_s),
        ]);
    Ok(())
}

/// A student's `history` input in the sidecar, its references and its control-loop step.
fn add_history_json(sidecar: &mut Value, h: usize, history: &[f32]) {
    sidecar["history"] = json!({
        "input": HISTORY_INPUT,
        "steps": h,
        "width": h * OBS_DIM,
        "order": "newest first: values [48 k, 48 (k + 1)) are the obs of k policy steps ago; slot 0 is this step's obs (the same values fed as `obs`)",
        "update": "each policy step, after building obs: history = [obs, history without its last 48 values]",
        "reset": "all zeros at the start of an episode, before the first update",
    });
    sidecar["reference"]["history"] = json!(json_rows(history, h * OBS_DIM));
    if let Some(steps) = sidecar["control_loop"].as_array_mut() {
        steps.insert(
            2,
            json!(format!("update history (1 x {}) as in `history` (zeros after a reset), then a = onnx(obs, history)[0]", h * OBS_DIM)),
        );
    }
}

/// The ONNX model's metadata: where its sidecar is, its iteration, config hash, observation layout.
fn onnx_metadata(
    onnx_path: &Path,
    progress: &Progress,
    config_hash: &str,
) -> Vec<(String, String)> {
    vec![
        (
            "rall.sidecar".to_string(),
            file_name(&sidecar_path(onnx_path)).unwrap_or_default(),
        ),
        ("rall.iteration".to_string(), progress.iteration.to_string()),
        ("rall.config_hash".to_string(), config_hash.to_string()),
        (
            "rall.obs_layout".to_string(),
            crate::env::observation::layout_string(),
        ),
    ]
}

/// The ONNX model's doc string.
fn model_doc(student: bool) -> &'static str {
    if student {
        "rall policy (RMA student): obs (batch x 48) and history (batch x H*48, newest first) -> raw actions (batch x 12); see the JSON sidecar for the controller"
    } else {
        "rall policy: obs (batch x 48) -> raw actions (batch x 12); see the JSON sidecar for the controller"
    }
}

/// Writes the ONNX file and its sidecar (each atomically); returns the sidecar's path.
fn write_export_files(onnx_path: &Path, bytes: &[u8], sidecar: &Value) -> Result<PathBuf> {
    if let Some(dir) = onnx_path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    crate::fsio::write_atomic(onnx_path, bytes)?;
    let side = sidecar_path(onnx_path);
    let text = serde_json::to_string_pretty(sidecar).context("serialising the sidecar")?;
    crate::fsio::write_atomic(&side, (text + "\n").as_bytes())?;
    Ok(side)
}

/// The deployment sections, the simulator statement and, for a policy reading
/// `obs` alone, the nominal trace; returns the policy step where the trace fell.
fn add_deployment(
    sidecar: &mut Value,
    learner: &Learner,
    config: &TrainConfig,
    (robot, scene): (&Robot, &Scene),
    student: bool,
) -> Result<Option<usize>> {
    let map = sidecar
        .as_object_mut()
        .context("the sidecar is a JSON object")?;
    map.extend(deploy::deployment_sections(config, robot)?);
    map.insert(
        "simulator".into(),
        deploy::simulator_json(config, scene.terrain.as_deref())?,
    );
    if student {
        return Ok(None);
    }
    let t = deploy::nominal_trace(learner, &config.env, deploy::TRACE_STEPS)?;
    map.insert("trace".into(), deploy::trace_json(&t, &config.env.control));
    Ok(t.fell_at_step)
}

fn dims_json(dims: &[Dim]) -> Vec<Value> {
    dims.iter()
        .map(|d| match d {
            Dim::Fixed(n) => json!(n),
            Dim::Named(s) => json!(s),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layer(inp: usize, out: usize, seed: u32) -> Dense {
        let v = |k: usize| {
            ((k as u32).wrapping_mul(2_654_435_761).wrapping_add(seed) % 1000) as f32 / 500.0 - 1.0
        };
        Dense {
            inp,
            out,
            weight: (0..inp * out).map(v).collect(),
            bias: (0..out).map(|k| v(k + 7)).collect(),
        }
    }

    #[test]
    fn the_normaliser_is_the_graphs_first_two_nodes() {
        let norm = ObsNormalizer {
            mean: vec![0.5, -1.0, 2.0, 0.0],
            inv_std: vec![0.5, 2.0, 1.0, 0.25],
        };
        let layers = vec![layer(4, 5, 1), layer(5, 3, 2)];
        let x = [0.3f32, -0.7, 1.9, 5.0];
        let normalised: Vec<f32> = x
            .iter()
            .zip(norm.mean.iter().zip(&norm.inv_std))
            .map(|(v, (m, s))| (v - m) * s)
            .collect();
        let plain = PolicyNet::GaussianMean {
            norm: None,
            layers: layers.clone(),
        };
        let with_norm = PolicyNet::GaussianMean {
            norm: Some(norm),
            layers,
        };
        assert_eq!(
            plain.forward_f64(&normalised),
            with_norm.forward_f64(&x),
            "the reference pass normalises first"
        );
        let ops: Vec<String> = with_norm
            .graph()
            .node
            .into_iter()
            .map(|n| n.op_type)
            .collect();
        assert_eq!(ops, ["Sub", "Mul", "Gemm", "Elu", "Gemm"]);
        let ops: Vec<String> = plain.graph().node.into_iter().map(|n| n.op_type).collect();
        assert_eq!(ops, ["Gemm", "Elu", "Gemm"]);
    }

    #[test]
    fn every_observation_field_has_a_definition() {
        for (name, _) in OBS_LAYOUT {
            assert!(field_definition(name).is_some(), "{name}");
        }
        let v = observation_json(&EnvConfig::default()).unwrap();
        assert_eq!(v["fields"].as_array().unwrap().len(), OBS_LAYOUT.len());
        assert_eq!(v["fields"][6]["offset"], 36);
    }

    #[test]
    fn fnv_matches_the_reference_vectors() {
        assert_eq!(fnv1a64_hex(""), "cbf29ce484222325");
        assert_eq!(fnv1a64_hex("a"), "af63dc4c8601ec8c");
    }
}
