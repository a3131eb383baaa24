//! What acts in a benchmark: a rall checkpoint's Gaussian mean, or an ONNX
//! network (with its JSON sidecar) trained anywhere. Benchmarks ask an
//! [`Actor`] for actions and never branch on where the policy came from.
//! rall's own exports run through rall's actor forward (see [`super::rall_graph`]),
//! so they give their checkpoint's numbers bit for bit; other graphs run through tract.

use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, ensure, Context, Result};
use tract_onnx::prelude::*;

use super::rall_graph::RallGraph;
use super::sidecar::{read_sidecar, ReferencePairs, SidecarPolicy};
use crate::env::{EnvConfig, ACT_DIM, OBS_DIM};
use crate::learn::Learner;

/// Deterministic actions for a batch of observation rows.
pub trait Actor {
    /// Raw actions (before clip and scale), `n x ACT_DIM`, for `obs` (`n` rows of
    /// rall's observation row).
    fn actions(&self, obs: &[f32]) -> Result<Vec<f32>>;
    /// The checkpoint's learner (critic, Gaussian), when there is one.
    fn learner(&self) -> Option<&Learner> {
        None
    }
}

impl Actor for Learner {
    fn actions(&self, obs: &[f32]) -> Result<Vec<f32>> {
        Ok(self.act_mean(obs))
    }
    fn learner(&self) -> Option<&Learner> {
        Some(self)
    }
}

/// A policy from a file: a rall checkpoint or an ONNX network.
pub enum Policy {
    Checkpoint(Box<Learner>),
    Onnx(Box<OnnxPolicy>),
}

impl Actor for Policy {
    fn actions(&self, obs: &[f32]) -> Result<Vec<f32>> {
        match self {
            Policy::Checkpoint(l) => l.actions(obs),
            Policy::Onnx(o) => o.actions(obs),
        }
    }
    fn learner(&self) -> Option<&Learner> {
        match self {
            Policy::Checkpoint(l) => Some(l),
            Policy::Onnx(_) => None,
        }
    }
}

/// Whether `path` names an ONNX file (by its extension).
pub fn is_onnx(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("onnx"))
}

/// An ONNX policy: one input `obs` (`batch x width`), one output (`batch x 12`
/// raw actions), the input gathered from rall's observation row as the sidecar
/// lays it out. A graph exported with a fixed batch of 1 runs robot by robot.
pub struct OnnxPolicy {
    /// The `.onnx` file (errors name it).
    path: std::path::PathBuf,
    network: Network,
    /// `input[k] = rall_obs[columns[k]]`.
    columns: Vec<usize>,
    /// `rall_action[joint_order[k]] = output[k]`.
    joint_order: Vec<usize>,
    /// The env the sidecar describes (PD, rates, scales, noise, commands, envelope).
    pub env: EnvConfig,
    /// Sidecar sections that were absent and took rall's defaults.
    pub defaulted: Vec<&'static str>,
}

/// What runs an ONNX graph.
enum Network {
    /// rall's own export, by rall's actor forward (bit-identical to the checkpoint).
    Rall(Box<RallGraph>),
    /// Any other graph, by tract; `one_row`: its input has a fixed batch of 1.
    Tract {
        plan: Arc<TypedRunnableModel>,
        one_row: bool,
    },
}

/// Which runtime [`OnnxPolicy::load_with`] uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OnnxRuntime {
    /// rall's actor forward for a graph of rall's own export form, tract otherwise.
    Auto,
    /// tract for every graph.
    Tract,
}

impl OnnxPolicy {
    /// Loads `path` (.onnx) and its sidecar (`.json` beside it); rall's own
    /// exports run through rall's actor forward, other graphs through tract.
    pub fn load(path: &Path) -> Result<OnnxPolicy> {
        OnnxPolicy::load_with(path, OnnxRuntime::Auto)
    }

    /// [`Self::load`], choosing the runtime.
    pub fn load_with(path: &Path, runtime: OnnxRuntime) -> Result<OnnxPolicy> {
        let side = read_sidecar(&crate::export::sidecar_path(path))?;
        let network = load_network(path, side.input_columns.len(), runtime)
            .with_context(|| format!("ONNX policy {}", path.display()))?;
        let SidecarPolicy {
            env,
            input_columns,
            joint_order,
            defaulted,
            reference,
        } = side;
        let policy = OnnxPolicy {
            path: path.to_path_buf(),
            network,
            columns: input_columns,
            joint_order,
            env,
            defaulted,
        };
        // one zero row through the network: a wrong-shaped output is refused now
        policy.actions(&[0.0; OBS_DIM])?;
        if let Some(r) = &reference {
            policy.reproduces(r)?;
        }
        Ok(policy)
    }

    /// Refuses a network that does not return the sidecar's reference actions
    /// for its reference observations (another network than the sidecar's, a
    /// normaliser left out, a runtime that computes otherwise).
    fn reproduces(&self, r: &ReferencePairs) -> Result<()> {
        let n = r.actions.len() / ACT_DIM;
        ensure!(
            r.observations.len() == n * self.columns.len(),
            "ONNX policy {}: the sidecar's reference observations hold {} values for {n} rows, but its fields make rows of {}",
            self.path.display(),
            r.observations.len(),
            self.columns.len()
        );
        let out = self.run(r.observations.clone(), n).with_context(|| {
            format!(
                "ONNX policy {}: the sidecar's reference observations",
                self.path.display()
            )
        })?;
        let worst = out
            .iter()
            .zip(&r.actions)
            .enumerate()
            .map(|(i, (a, b))| (i, (*a as f64 - *b as f64).abs()))
            .fold((0, 0.0f64), |m, d| if d.1 > m.1 { d } else { m });
        ensure!(
            worst.1 <= r.tolerance_abs,
            "ONNX policy {}: for the sidecar's reference observation {} the network returns {} as action {} where the sidecar says {} (off by {:.3e}, tolerance {:.1e}): the network is not the one its sidecar describes, or its input is not laid out as the sidecar's fields say",
            self.path.display(),
            worst.0 / ACT_DIM,
            out[worst.0],
            worst.0 % ACT_DIM,
            r.actions[worst.0],
            worst.1,
            r.tolerance_abs
        );
        Ok(())
    }

    /// Width of the network's input.
    pub fn input_width(&self) -> usize {
        self.columns.len()
    }

    /// Whether rall's actor forward runs the graph (rall's own export form);
    /// otherwise tract does.
    pub fn runs_on_rall_forward(&self) -> bool {
        matches!(self.network, Network::Rall(_))
    }

    /// The network's raw output for `n` input rows (`n x width`), `n x ACT_DIM`.
    fn run(&self, input: Vec<f32>, n: usize) -> Result<Vec<f32>> {
        let w = self.columns.len();
        let out = match &self.network {
            Network::Rall(g) => g.actions(&input, n),
            Network::Tract {
                plan,
                one_row: false,
            } => run_plan(plan, input, n, w)?,
            Network::Tract {
                plan,
                one_row: true,
            } => {
                let mut out = Vec::with_capacity(n * ACT_DIM);
                for row in input.chunks_exact(w) {
                    out.extend(run_plan(plan, row.to_vec(), 1, w)?);
                }
                out
            }
        };
        ensure!(
            out.len() == n * ACT_DIM,
            "the network returned {} values for {n} observations, expected {n} x {ACT_DIM}",
            out.len()
        );
        Ok(out)
    }
}

/// Runs tract's `plan` on `n` rows of `w` values.
fn run_plan(
    plan: &Arc<TypedRunnableModel>,
    input: Vec<f32>,
    n: usize,
    w: usize,
) -> Result<Vec<f32>> {
    let x = tract_ndarray::Array2::from_shape_vec((n, w), input)?;
    let out = plan.run(tvec!(Tensor::from(x).into()))?;
    let view = out[0].to_plain_array_view::<f32>()?;
    ensure!(
        view.shape() == [n, ACT_DIM],
        "the network returned shape {:?} for {n} observations, expected [{n}, {ACT_DIM}]",
        view.shape()
    );
    Ok(view.as_slice().context("a contiguous output")?.to_vec())
}

impl Actor for OnnxPolicy {
    fn actions(&self, obs: &[f32]) -> Result<Vec<f32>> {
        self.actions_in_rall_order(obs)
            .with_context(|| format!("ONNX policy {}", self.path.display()))
    }
}

impl OnnxPolicy {
    /// [`Actor::actions`] without the file's name on errors.
    fn actions_in_rall_order(&self, obs: &[f32]) -> Result<Vec<f32>> {
        ensure!(
            obs.len().is_multiple_of(OBS_DIM),
            "observation rows of {OBS_DIM} expected, got {} values",
            obs.len()
        );
        let n = obs.len() / OBS_DIM;
        let w = self.columns.len();
        let mut input = Vec::with_capacity(n * w);
        for row in obs.chunks_exact(OBS_DIM) {
            input.extend(self.columns.iter().map(|&c| row[c]));
        }
        let out = self.run(input, n)?;
        let mut actions = vec![0.0f32; n * ACT_DIM];
        for (row, out) in actions
            .chunks_exact_mut(ACT_DIM)
            .zip(out.chunks_exact(ACT_DIM))
        {
            for (k, &j) in self.joint_order.iter().enumerate() {
                row[j] = out[k];
            }
        }
        Ok(actions)
    }
}

/// rall's forward for a graph of rall's export form (unless `runtime` asks for
/// tract), else tract's plan; either checked to take one `batch x width` input.
fn load_network(path: &Path, width: usize, runtime: OnnxRuntime) -> Result<Network> {
    if runtime == OnnxRuntime::Auto {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        if let Some(g) = RallGraph::recognise(&bytes) {
            let w = g.input_width();
            ensure!(
                w == width,
                "the network's input is {w} wide but the sidecar's observation.fields hold {width} values"
            );
            return Ok(Network::Rall(Box::new(g)));
        }
    }
    let (plan, one_row) = load_plan(path, width)?;
    Ok(Network::Tract { plan, one_row })
}

/// The optimised tract plan of `path`, checked to take one `batch x width`
/// input, and whether that batch is fixed at 1 (the plan then runs robot by
/// robot). Another fixed batch is refused.
fn load_plan(path: &Path, width: usize) -> Result<(Arc<TypedRunnableModel>, bool)> {
    let model = tract_onnx::onnx()
        .model_for_path(path)
        .with_context(|| format!("reading {}", path.display()))?;
    let typed = model.into_typed().context("tract cannot type the graph")?;
    let inputs = typed.input_outlets()?.len();
    if inputs != 1 {
        bail!(
            "the network has {inputs} inputs; rall feeds one (`obs`, the sidecar's observation.fields) — an RMA student's `history` input is not supported for outside policies"
        );
    }
    let fact = typed.input_fact(0)?;
    ensure!(
        fact.shape.len() == 2,
        "the network's input has shape {:?}, expected [batch, {width}]",
        fact.shape
    );
    if let Ok(w) = fact.shape[1].to_i64() {
        ensure!(
            w == width as i64,
            "the network's input is {w} wide but the sidecar's observation.fields hold {width} values"
        );
    }
    let fixed_batch = fact.shape[0].to_i64().ok();
    if let Some(b) = fixed_batch.filter(|&b| b != 1) {
        bail!(
            "the network's input has a fixed batch of {b}, and rall feeds any number of robots: export it with a dynamic batch axis (torch.onnx.export(..., dynamic_axes={{\"obs\": {{0: \"batch\"}}}})) or a batch of 1, which rall runs robot by robot"
        );
    }
    let plan = typed
        .into_optimized()
        .context("tract cannot optimise the graph")?
        .into_runnable()?;
    Ok((plan, fixed_batch == Some(1)))
}
