//! rall's own exports, run by rall's actor forward instead of tract.
//!
//! An ONNX graph of exactly the form `rall export` writes for a Gaussian actor
//! (`obs`, optionally `Mul(Sub(obs, mean), inv_std)`, then `Gemm`, `Elu`, ...,
//! `Gemm`) is read back into a [`GaussianActor`], whose `mean` is the code a
//! checkpoint's actor runs, with the normaliser applied as the checkpoint's
//! normaliser applies it. Benchmarks of an export then give the checkpoint's
//! numbers bit for bit: tract sums its matrix products in another order
//! (actions differ by about 5e-7), and a robot falling under a push amplifies
//! that into another fall step. Any other graph returns `None` (tract runs it).

use std::collections::HashMap;

use prost::Message;
use rand::SeedableRng;

use crate::export::onnx::{
    AttributeProto, ModelProto, NodeProto, TensorProto, DATA_TYPE_FLOAT, NORM_INV_STD, NORM_MEAN,
};
use crate::learn::nets::GaussianActor;

/// A dense ELU network read from rall's own export.
pub struct RallGraph {
    actor: GaussianActor,
    /// `(mean, inv_std)` of the normaliser, applied as `(x - mean) * inv_std`.
    norm: Option<(Vec<f32>, Vec<f32>)>,
}

/// One `Gemm` layer as rall stores it: `in x out` row-major weight, bias.
struct Layer {
    inp: usize,
    out: usize,
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl RallGraph {
    /// The network of the ONNX `bytes` when it has the form rall exports, else `None`.
    pub fn recognise(bytes: &[u8]) -> Option<RallGraph> {
        let graph = ModelProto::decode(bytes).ok()?.graph?;
        let inits: HashMap<&str, &TensorProto> = graph
            .initializer
            .iter()
            .map(|t| (t.name.as_str(), t))
            .collect();
        let inputs: Vec<&str> = graph
            .input
            .iter()
            .map(|i| i.name.as_str())
            .filter(|n| !inits.contains_key(n))
            .collect();
        let ([input], [output]) = (inputs.as_slice(), graph.output.as_slice()) else {
            return None;
        };
        let mut nodes = graph.node.iter().peekable();
        let mut x = input.to_string();
        let mut norm = None;
        if nodes.peek().is_some_and(|n| n.op_type == "Sub") {
            let (sub, mul) = (nodes.next()?, nodes.next()?);
            let mean = operand(sub, "Sub", &x, NORM_MEAN, &inits)?;
            let inv_std = operand(mul, "Mul", &sub.output[0], NORM_INV_STD, &inits)?;
            x = mul.output[0].clone();
            norm = Some((mean, inv_std));
        }
        let mut layers: Vec<Layer> = Vec::new();
        loop {
            let node = nodes.next()?;
            let layer = gemm(node, &x, &inits)?;
            if layers.last().is_some_and(|p| p.out != layer.inp) {
                return None;
            }
            layers.push(layer);
            x = node.output[0].clone();
            let Some(elu) = nodes.next() else { break };
            if !is_unit_elu(elu, &x) {
                return None;
            }
            x = elu.output[0].clone();
        }
        if x != output.name {
            return None;
        }
        if let Some((m, s)) = &norm {
            if m.len() != layers[0].inp || s.len() != layers[0].inp {
                return None;
            }
        }
        Some(RallGraph {
            actor: actor_of(&layers)?,
            norm,
        })
    }

    /// Width of the network's input.
    pub fn input_width(&self) -> usize {
        self.actor.obs_dim
    }

    /// Raw actions for `n` input rows, computed as a checkpoint's actor computes them.
    pub fn actions(&self, input: &[f32], n: usize) -> Vec<f32> {
        match &self.norm {
            None => self.actor.mean(input, n),
            Some((mean, inv_std)) => {
                let mut rows = input.to_vec();
                for row in rows.chunks_exact_mut(mean.len()) {
                    for ((x, m), s) in row.iter_mut().zip(mean).zip(inv_std) {
                        *x = (*x - m) * s;
                    }
                }
                self.actor.mean(&rows, n)
            }
        }
    }
}

/// The 1-D float initializer `name` that `node` (`op(x, name)`) applies to `x`.
fn operand(
    node: &NodeProto,
    op: &str,
    x: &str,
    name: &str,
    inits: &HashMap<&str, &TensorProto>,
) -> Option<Vec<f32>> {
    let plain = node.op_type == op && node.attribute.is_empty() && default_domain(node);
    if !(plain && node.input == [x, name] && node.output.len() == 1) {
        return None;
    }
    let t = inits.get(name)?;
    (t.dims.len() == 1).then_some(())?;
    floats(t)
}

/// A `Gemm(x, W, b)` with alpha = beta = 1 and no transposed `x`, as a layer
/// (`transB = 1` is transposed back to rall's `in x out`).
fn gemm(node: &NodeProto, x: &str, inits: &HashMap<&str, &TensorProto>) -> Option<Layer> {
    if node.op_type != "Gemm" || !default_domain(node) || node.input.len() != 3 {
        return None;
    }
    if node.input[0] != x || node.output.len() != 1 {
        return None;
    }
    let mut trans_b = false;
    for a in &node.attribute {
        match a.name.as_str() {
            "alpha" | "beta" if a.f == 1.0 => {}
            "transA" if a.i == 0 => {}
            "transB" if a.i == 0 || a.i == 1 => trans_b = a.i == 1,
            _ => return None,
        }
    }
    let (w, b) = (
        inits.get(node.input[1].as_str())?,
        inits.get(node.input[2].as_str())?,
    );
    let [rows, cols] = w.dims.as_slice() else {
        return None;
    };
    let (rows, cols) = (usize::try_from(*rows).ok()?, usize::try_from(*cols).ok()?);
    let stored = floats(w)?;
    let (inp, out, weight) = if trans_b {
        let t = (0..rows * cols)
            .map(|k| stored[(k % rows) * cols + k / rows])
            .collect();
        (cols, rows, t)
    } else {
        (rows, cols, stored)
    };
    let bias = floats(b)?;
    let bias_dims_fit = matches!(b.dims.as_slice(), [o] | [1, o] if *o == out as i64);
    bias_dims_fit.then_some(Layer {
        inp,
        out,
        weight,
        bias,
    })
}

/// `Elu` with alpha 1 (rall's activation) reading `x`.
fn is_unit_elu(node: &NodeProto, x: &str) -> bool {
    let unit = |a: &AttributeProto| a.name == "alpha" && a.f == 1.0;
    node.op_type == "Elu"
        && default_domain(node)
        && node.input == [x]
        && node.output.len() == 1
        && node.attribute.iter().all(unit)
}

fn default_domain(node: &NodeProto) -> bool {
    node.domain.is_empty() || node.domain == "ai.onnx"
}

/// The values of a float tensor (raw little-endian bytes or `float_data`).
fn floats(t: &TensorProto) -> Option<Vec<f32>> {
    if t.data_type != DATA_TYPE_FLOAT {
        return None;
    }
    let len = t
        .dims
        .iter()
        .try_fold(1usize, |n, &d| n.checked_mul(usize::try_from(d).ok()?))?;
    let values: Vec<f32> = if t.raw_data.is_empty() {
        t.float_data.clone()
    } else {
        t.raw_data
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    };
    (values.len() == len).then_some(values)
}

/// A Gaussian actor whose mean network has `layers`' weights (rall's actor
/// type, so its forward pass is the checkpoint's).
fn actor_of(layers: &[Layer]) -> Option<GaussianActor> {
    let (first, last) = (layers.first()?, layers.last()?);
    let hidden: Vec<usize> = layers[..layers.len() - 1].iter().map(|l| l.out).collect();
    // the initial weights are overwritten below
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut actor = GaussianActor::new(first.inp, last.out, &hidden, 1.0, &mut rng);
    for (i, l) in layers.iter().enumerate() {
        for (name, data) in [
            (format!("l{i}.weight"), &l.weight),
            (format!("l{i}.bias"), &l.bias),
        ] {
            let ps = &mut actor.params;
            let e = ps.entries.iter().find(|e| e.name == name)?;
            if e.len() != data.len() {
                return None;
            }
            ps.data[e.offset..e.offset + e.len()].copy_from_slice(data);
        }
    }
    Some(actor)
}
