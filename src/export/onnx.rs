//! Writing ONNX without a new dependency: the subset of the ONNX protobuf schema
//! that an MLP policy needs, hand-declared as `prost` messages (field numbers from
//! the official `onnx/onnx.proto`, IR version 7 = opset 13), and a graph builder
//! for dense ELU networks (`Gemm` + `Elu`, after an optional normaliser `Sub` + `Mul`).
//!
//! onnx.proto is proto2; prost writes proto3-style fields, i.e. omits fields equal
//! to their default. Every field we rely on has the same default in both (0, "",
//! empty), so a proto2 reader decodes what we meant.

use prost::Message;

/// IR version 7 is the one that introduced opset 13 (ONNX 1.8).
pub const IR_VERSION: i64 = 7;
/// Default-domain operator set of the exported graphs.
pub const OPSET: i64 = 13;
/// Name of the dynamic batch dimension.
pub const BATCH_DIM: &str = "batch";

/// `TensorProto.DataType.FLOAT`.
pub const DATA_TYPE_FLOAT: i32 = 1;
/// `AttributeProto.AttributeType.FLOAT`.
const ATTR_FLOAT: i32 = 1;
const ATTR_INT: i32 = 2;

#[derive(Clone, PartialEq, Message)]
pub struct ModelProto {
    #[prost(int64, tag = "1")]
    pub ir_version: i64,
    #[prost(string, tag = "2")]
    pub producer_name: String,
    #[prost(string, tag = "3")]
    pub producer_version: String,
    #[prost(string, tag = "4")]
    pub domain: String,
    #[prost(int64, tag = "5")]
    pub model_version: i64,
    #[prost(string, tag = "6")]
    pub doc_string: String,
    #[prost(message, optional, tag = "7")]
    pub graph: Option<GraphProto>,
    #[prost(message, repeated, tag = "8")]
    pub opset_import: Vec<OperatorSetIdProto>,
    #[prost(message, repeated, tag = "14")]
    pub metadata_props: Vec<StringStringEntryProto>,
}

#[derive(Clone, PartialEq, Message)]
pub struct OperatorSetIdProto {
    /// Empty: the default `ai.onnx` domain.
    #[prost(string, tag = "1")]
    pub domain: String,
    #[prost(int64, tag = "2")]
    pub version: i64,
}

#[derive(Clone, PartialEq, Message)]
pub struct StringStringEntryProto {
    #[prost(string, tag = "1")]
    pub key: String,
    #[prost(string, tag = "2")]
    pub value: String,
}

#[derive(Clone, PartialEq, Message)]
pub struct GraphProto {
    #[prost(message, repeated, tag = "1")]
    pub node: Vec<NodeProto>,
    #[prost(string, tag = "2")]
    pub name: String,
    #[prost(message, repeated, tag = "5")]
    pub initializer: Vec<TensorProto>,
    #[prost(string, tag = "10")]
    pub doc_string: String,
    #[prost(message, repeated, tag = "11")]
    pub input: Vec<ValueInfoProto>,
    #[prost(message, repeated, tag = "12")]
    pub output: Vec<ValueInfoProto>,
    #[prost(message, repeated, tag = "13")]
    pub value_info: Vec<ValueInfoProto>,
}

#[derive(Clone, PartialEq, Message)]
pub struct NodeProto {
    #[prost(string, repeated, tag = "1")]
    pub input: Vec<String>,
    #[prost(string, repeated, tag = "2")]
    pub output: Vec<String>,
    #[prost(string, tag = "3")]
    pub name: String,
    #[prost(string, tag = "4")]
    pub op_type: String,
    #[prost(message, repeated, tag = "5")]
    pub attribute: Vec<AttributeProto>,
    #[prost(string, tag = "6")]
    pub doc_string: String,
    #[prost(string, tag = "7")]
    pub domain: String,
}

#[derive(Clone, PartialEq, Message)]
pub struct AttributeProto {
    #[prost(string, tag = "1")]
    pub name: String,
    #[prost(float, tag = "2")]
    pub f: f32,
    #[prost(int64, tag = "3")]
    pub i: i64,
    #[prost(bytes = "vec", tag = "4")]
    pub s: Vec<u8>,
    #[prost(message, optional, tag = "5")]
    pub t: Option<TensorProto>,
    #[prost(float, repeated, tag = "7")]
    pub floats: Vec<f32>,
    #[prost(int64, repeated, tag = "8")]
    pub ints: Vec<i64>,
    #[prost(string, tag = "13")]
    pub doc_string: String,
    /// `AttributeType`: FLOAT 1, INT 2, STRING 3, TENSOR 4, FLOATS 6, INTS 7.
    #[prost(int32, tag = "20")]
    pub r#type: i32,
}

#[derive(Clone, PartialEq, Message)]
pub struct TensorProto {
    #[prost(int64, repeated, tag = "1")]
    pub dims: Vec<i64>,
    #[prost(int32, tag = "2")]
    pub data_type: i32,
    #[prost(float, repeated, tag = "4")]
    pub float_data: Vec<f32>,
    #[prost(string, tag = "8")]
    pub name: String,
    /// Little-endian values, row-major.
    #[prost(bytes = "vec", tag = "9")]
    pub raw_data: Vec<u8>,
    #[prost(string, tag = "12")]
    pub doc_string: String,
}

#[derive(Clone, PartialEq, Message)]
pub struct ValueInfoProto {
    #[prost(string, tag = "1")]
    pub name: String,
    #[prost(message, optional, tag = "2")]
    pub r#type: Option<TypeProto>,
    #[prost(string, tag = "3")]
    pub doc_string: String,
}

#[derive(Clone, PartialEq, Message)]
pub struct TypeProto {
    /// The `tensor_type` member of the `value` oneof (the only one we write).
    #[prost(message, optional, tag = "1")]
    pub tensor_type: Option<TypeProtoTensor>,
}

/// `TypeProto.Tensor`.
#[derive(Clone, PartialEq, Message)]
pub struct TypeProtoTensor {
    #[prost(int32, tag = "1")]
    pub elem_type: i32,
    #[prost(message, optional, tag = "2")]
    pub shape: Option<TensorShapeProto>,
}

#[derive(Clone, PartialEq, Message)]
pub struct TensorShapeProto {
    #[prost(message, repeated, tag = "1")]
    pub dim: Vec<Dimension>,
}

/// `TensorShapeProto.Dimension`: a fixed size or a named (dynamic) one.
#[derive(Clone, PartialEq, Message)]
pub struct Dimension {
    #[prost(oneof = "DimensionValue", tags = "1, 2")]
    pub value: Option<DimensionValue>,
}

#[derive(Clone, PartialEq, prost::Oneof)]
pub enum DimensionValue {
    #[prost(int64, tag = "1")]
    DimValue(i64),
    #[prost(string, tag = "2")]
    DimParam(String),
}

/// One dimension of a graph input or output.
#[derive(Clone, Debug, PartialEq)]
pub enum Dim {
    Fixed(usize),
    Named(String),
}

/// A float tensor graph input/output with the given shape.
pub fn float_value_info(name: &str, dims: &[Dim], doc: &str) -> ValueInfoProto {
    let dim = dims
        .iter()
        .map(|d| Dimension {
            value: Some(match d {
                Dim::Fixed(n) => DimensionValue::DimValue(*n as i64),
                Dim::Named(s) => DimensionValue::DimParam(s.clone()),
            }),
        })
        .collect();
    ValueInfoProto {
        name: name.into(),
        r#type: Some(TypeProto {
            tensor_type: Some(TypeProtoTensor {
                elem_type: DATA_TYPE_FLOAT,
                shape: Some(TensorShapeProto { dim }),
            }),
        }),
        doc_string: doc.into(),
    }
}

/// A float initializer (row-major `data` of shape `dims`), stored as raw little-endian bytes.
pub fn float_tensor(name: &str, dims: &[usize], data: &[f32]) -> TensorProto {
    debug_assert_eq!(dims.iter().product::<usize>(), data.len());
    TensorProto {
        dims: dims.iter().map(|&d| d as i64).collect(),
        data_type: DATA_TYPE_FLOAT,
        name: name.into(),
        raw_data: data.iter().flat_map(|v| v.to_le_bytes()).collect(),
        ..Default::default()
    }
}

fn node(op: &str, name: &str, inputs: &[&str], output: &str) -> NodeProto {
    NodeProto {
        input: inputs.iter().map(|s| s.to_string()).collect(),
        output: vec![output.into()],
        name: name.into(),
        op_type: op.into(),
        ..Default::default()
    }
}

/// One dense layer `y = x W + b` with `W` stored `in x out` (rall's layout).
#[derive(Clone, Debug, PartialEq)]
pub struct Dense {
    pub inp: usize,
    pub out: usize,
    /// Row-major `inp x out`.
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
}

/// Appends an MLP `input -> Gemm -> Elu -> ... -> Gemm -> output` to `graph`
/// (ELU alpha 1 between layers, none after the last). `prefix` names its
/// initializers and nodes. `Gemm` with `transB = 0` takes `W` as stored
/// (`in x out`), so no weight is transposed.
pub fn push_mlp(graph: &mut GraphProto, prefix: &str, layers: &[Dense], input: &str, output: &str) {
    let mut x = input.to_string();
    for (i, l) in layers.iter().enumerate() {
        let w = format!("{prefix}l{i}.weight");
        let b = format!("{prefix}l{i}.bias");
        graph
            .initializer
            .push(float_tensor(&w, &[l.inp, l.out], &l.weight));
        graph.initializer.push(float_tensor(&b, &[l.out], &l.bias));
        let last = i + 1 == layers.len();
        let y = if last {
            output.to_string()
        } else {
            format!("{prefix}l{i}.linear")
        };
        graph.node.push(node(
            "Gemm",
            &format!("{prefix}l{i}.gemm"),
            &[&x, &w, &b],
            &y,
        ));
        if last {
            break;
        }
        let h = format!("{prefix}l{i}.elu");
        let mut elu = node("Elu", &h, &[&y], &h);
        elu.attribute.push(AttributeProto {
            name: "alpha".into(),
            f: 1.0,
            r#type: ATTR_FLOAT,
            ..Default::default()
        });
        graph.node.push(elu);
        x = h;
    }
}

/// Appends the observation normaliser `output = (input - mean) * inv_std` to
/// `graph` (`Sub`, then `Mul`; initializers `obs_norm.mean`, `obs_norm.inv_std`).
pub fn push_normalizer(
    graph: &mut GraphProto,
    mean: &[f32],
    inv_std: &[f32],
    input: &str,
    output: &str,
) {
    let (m, s, centred) = (NORM_MEAN, NORM_INV_STD, "obs_norm.centred");
    graph.initializer.push(float_tensor(m, &[mean.len()], mean));
    graph
        .initializer
        .push(float_tensor(s, &[inv_std.len()], inv_std));
    graph
        .node
        .push(node("Sub", "obs_norm.sub", &[input, m], centred));
    graph
        .node
        .push(node("Mul", "obs_norm.mul", &[centred, s], output));
}

/// Initializer names of the normaliser [`push_normalizer`] writes.
pub const NORM_MEAN: &str = "obs_norm.mean";
pub const NORM_INV_STD: &str = "obs_norm.inv_std";

/// Appends `output = Concat(inputs, axis)` to `graph`.
pub fn push_concat(graph: &mut GraphProto, name: &str, inputs: &[&str], axis: i64, output: &str) {
    let mut n = node("Concat", name, inputs, output);
    n.attribute.push(AttributeProto {
        name: "axis".into(),
        i: axis,
        r#type: ATTR_INT,
        ..Default::default()
    });
    graph.node.push(n);
}

/// Wraps a graph into a model (IR 7, default-domain opset 13) with metadata.
pub fn model(graph: GraphProto, doc: &str, metadata: &[(String, String)]) -> ModelProto {
    ModelProto {
        ir_version: IR_VERSION,
        producer_name: "rall".into(),
        producer_version: env!("CARGO_PKG_VERSION").into(),
        domain: String::new(),
        model_version: 1,
        doc_string: doc.into(),
        graph: Some(graph),
        opset_import: vec![OperatorSetIdProto {
            domain: String::new(),
            version: OPSET,
        }],
        metadata_props: metadata
            .iter()
            .map(|(k, v)| StringStringEntryProto {
                key: k.clone(),
                value: v.clone(),
            })
            .collect(),
    }
}

/// The protobuf bytes of `model`.
pub fn encode(model: &ModelProto) -> Vec<u8> {
    model.encode_to_vec()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_through_prost() {
        let mut g = GraphProto {
            name: "t".into(),
            ..Default::default()
        };
        let layers = [
            Dense {
                inp: 2,
                out: 3,
                weight: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
                bias: vec![0.1, 0.2, 0.3],
            },
            Dense {
                inp: 3,
                out: 1,
                weight: vec![1.0, -1.0, 0.5],
                bias: vec![0.0],
            },
        ];
        push_mlp(&mut g, "actor.", &layers, "obs", "actions");
        let m = model(g, "doc", &[("k".into(), "v".into())]);
        let bytes = encode(&m);
        let back = ModelProto::decode(bytes.as_slice()).unwrap();
        assert_eq!(back, m);
        let g = back.graph.unwrap();
        let ops: Vec<&str> = g.node.iter().map(|n| n.op_type.as_str()).collect();
        assert_eq!(ops, ["Gemm", "Elu", "Gemm"]);
        assert_eq!(g.node[2].output, ["actions"]);
        assert_eq!(g.initializer[0].dims, [2, 3]);
        assert_eq!(g.initializer[0].raw_data.len(), 6 * 4);
    }
}
