//! A run's policy for a robot stack: the ONNX model of its mean action and the card (JSON)
//! that says how to feed it and read it, and what it is known to do (`pbrl export`).
//!
//! The model (opset 13, IR version 7) maps raw observations to actions:
//!
//! ```text
//! obs    float32 [N, 25]   the feeding world's observation, as the world gives it
//!   -> (obs - obs_mean) * obs_inv_std, clipped to +-obs_clip   (the run's normaliser)
//!   -> Gemm, Relu, ..., Gemm   (the policy's MLP; the last layer's mean half)
//!   -> Tanh
//! action float32 [N, 7]    in [-1, 1]: joint position targets q + action_scale * action
//! ```

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
pub use onnx_protobuf::Message;
use onnx_protobuf::{
    attribute_proto::AttributeType, tensor_proto::DataType, tensor_shape_proto, type_proto,
    AttributeProto, GraphProto, ModelProto, NodeProto, OperatorSetIdProto, StringStringEntryProto,
    TensorProto, TensorShapeProto, TypeProto, ValueInfoProto,
};
use pbrl_common::wire::Weights;
use serde::{Deserialize, Serialize};

/// The ONNX opset the model uses (Gemm, Relu, Tanh, Sub, Mul, Clip with min/max inputs).
pub const OPSET: i64 = 13;
/// The IR version that goes with opset 13.
pub const IR_VERSION: i64 = 7;

/// One number of the observation or action vector: its name, unit and what it is.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Slot {
    pub index: usize,
    pub name: String,
    pub unit: String,
}

/// The card that goes with an exported model: what a robot stack needs to feed it and read
/// it, and what the policy is known to do.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Card {
    /// "pbrl policy card", version 1.
    pub format: String,
    pub version: u32,
    /// The model file (as written) and its ONNX opset and IR version.
    pub model: String,
    pub opset: i64,
    pub ir_version: i64,
    /// Input and output names and shapes ("N" is the batch).
    pub input: String,
    pub input_shape: Vec<String>,
    pub output: String,
    pub output_shape: Vec<String>,
    /// The observation's layout (robot base frame) and the action's.
    pub observation: Vec<Slot>,
    pub action: Vec<Slot>,
    /// What an action means: joint position targets `q + action_scale * action` (rad),
    /// each action number in [action_low, action_high].
    pub action_meaning: String,
    pub action_scale: f32,
    pub action_low: f32,
    pub action_high: f32,
    /// Env steps per second of control.
    pub control_hz: f32,
    /// The normaliser inside the model (for a reader; the model applies it).
    pub obs_clip: f32,
    /// The run: folder name, algorithm, reward, seed, the checkpoint's env steps and
    /// weights version.
    pub run: String,
    pub algo: String,
    pub reward: String,
    pub seed: u64,
    pub env_steps: u64,
    pub weights_version: u64,
    /// The person it was trained for (the world's profile) and the whole world config.
    pub person: serde_json::Value,
    pub world: serde_json::Value,
    /// The labels it learnt from (null without a label store): asked, answered, equal,
    /// skipped.
    pub labels: Option<serde_json::Value>,
    /// Its evaluation for that person: episodes, and each measure's mean and 95% interval.
    pub evaluation: Option<serde_json::Value>,
}

/// The feeding world's observation (`shared/feeding.md`), robot base frame.
pub const OBSERVATION: [(&str, &str); 25] = [
    ("spoon_x", "m"),
    ("spoon_y", "m"),
    ("spoon_z", "m"),
    ("spoon_qx", "quaternion"),
    ("spoon_qy", "quaternion"),
    ("spoon_qz", "quaternion"),
    ("spoon_qw", "quaternion"),
    ("spoon_minus_mouth_x", "m"),
    ("spoon_minus_mouth_y", "m"),
    ("spoon_minus_mouth_z", "m"),
    ("joint_s0", "rad in [-pi, pi]"),
    ("joint_s1", "rad in [-pi, pi]"),
    ("joint_e0", "rad in [-pi, pi]"),
    ("joint_e1", "rad in [-pi, pi]"),
    ("joint_w0", "rad in [-pi, pi]"),
    ("joint_w1", "rad in [-pi, pi]"),
    ("joint_w2", "rad in [-pi, pi]"),
    ("head_x", "m"),
    ("head_y", "m"),
    ("head_z", "m"),
    ("head_qx", "quaternion"),
    ("head_qy", "quaternion"),
    ("head_qz", "quaternion"),
    ("head_qw", "quaternion"),
    ("spoon_contact_force", "N"),
];

/// The arm's joints, in action order.
pub const JOINTS: [&str; 7] = ["s0", "s1", "e0", "e1", "w0", "w1", "w2"];

fn float_tensor(name: &str, dims: &[i64], data: &[f32]) -> TensorProto {
    let mut t = TensorProto::new();
    t.name = name.into();
    t.dims = dims.to_vec();
    t.data_type = DataType::FLOAT as i32;
    t.raw_data = data.iter().flat_map(|x| x.to_le_bytes()).collect();
    t
}

fn value_info(name: &str, dims: &[tensor_shape_proto::dimension::Value]) -> ValueInfoProto {
    let mut shape = TensorShapeProto::new();
    shape.dim = dims
        .iter()
        .map(|d| {
            let mut x = tensor_shape_proto::Dimension::new();
            x.value = Some(d.clone());
            x
        })
        .collect();
    let mut tensor = type_proto::Tensor::new();
    tensor.elem_type = DataType::FLOAT as i32;
    tensor.shape = Some(shape).into();
    let mut ty = TypeProto::new();
    ty.value = Some(type_proto::Value::TensorType(tensor));
    let mut v = ValueInfoProto::new();
    v.name = name.into();
    v.type_ = Some(ty).into();
    v
}

fn node(op: &str, inputs: &[&str], output: &str, attrs: Vec<AttributeProto>) -> NodeProto {
    let mut n = NodeProto::new();
    n.op_type = op.into();
    n.name = output.into();
    n.input = inputs.iter().map(|s| s.to_string()).collect();
    n.output = vec![output.into()];
    n.attribute = attrs;
    n
}

fn int_attr(name: &str, v: i64) -> AttributeProto {
    let mut a = AttributeProto::new();
    a.name = name.into();
    a.type_ = AttributeType::INT.into();
    a.i = v;
    a
}

/// One linear layer of the policy: the weight's shape [out, in], its values and the bias.
type Layer<'a> = (&'a [usize], &'a [f32], &'a [f32]);

/// The policy's layers `pi.l<i>` in order.
fn layers(w: &Weights) -> Result<Vec<Layer<'_>>> {
    let mut out = Vec::new();
    for i in 0.. {
        let find = |suffix: &str| {
            w.tensors
                .iter()
                .find(|t| t.name == format!("pi.l{i}.{suffix}"))
        };
        match (find("weight"), find("bias")) {
            (Some(wt), Some(b)) => {
                if wt.shape.len() != 2 || b.shape != [wt.shape[0]] {
                    bail!(
                        "pi.l{i}: weight {:?} and bias {:?} are not a linear layer",
                        wt.shape,
                        b.shape
                    );
                }
                out.push((wt.shape.as_slice(), wt.data.as_slice(), b.data.as_slice()));
            }
            (None, None) => break,
            _ => bail!("pi.l{i}: a weight without a bias or a bias without a weight"),
        }
    }
    if out.is_empty() {
        bail!("the weights hold no policy layers pi.l<i>");
    }
    Ok(out)
}

/// The ONNX model of `w`'s mean action, raw observations in.
pub fn model(w: &Weights, doc: &str, meta: &[(&str, String)]) -> Result<ModelProto> {
    use tensor_shape_proto::dimension::Value as Dim;
    let (obs_dim, act_dim) = (w.obs_dim as usize, w.act_dim as usize);
    let layers = layers(w)?;
    if layers[0].0[1] != obs_dim || layers.last().map(|l| l.0[0]) != Some(2 * act_dim) {
        bail!(
            "the policy maps {} numbers to {}, not {obs_dim} to 2 x {act_dim}",
            layers[0].0[1],
            layers[layers.len() - 1].0[0]
        );
    }
    if w.obs_mean.len() != obs_dim || w.obs_var.len() != obs_dim {
        bail!("the normaliser is not {obs_dim} long");
    }
    let mut g = GraphProto::new();
    g.name = "pbrl_policy".into();
    // NOTE: as `RunningNorm::apply`: (x - mean) / sqrt(var + 1e-8), clipped.
    let inv_std: Vec<f32> = w
        .obs_var
        .iter()
        .map(|v| (1.0 / (*v as f64 + 1e-8).sqrt()) as f32)
        .collect();
    g.initializer
        .push(float_tensor("obs_mean", &[obs_dim as i64], &w.obs_mean));
    g.initializer
        .push(float_tensor("obs_inv_std", &[obs_dim as i64], &inv_std));
    g.initializer
        .push(float_tensor("obs_clip_low", &[], &[-w.obs_clip]));
    g.initializer
        .push(float_tensor("obs_clip_high", &[], &[w.obs_clip]));
    g.node
        .push(node("Sub", &["obs", "obs_mean"], "obs_centred", vec![]));
    g.node.push(node(
        "Mul",
        &["obs_centred", "obs_inv_std"],
        "obs_scaled",
        vec![],
    ));
    g.node.push(node(
        "Clip",
        &["obs_scaled", "obs_clip_low", "obs_clip_high"],
        "obs_normalised",
        vec![],
    ));
    let mut h = "obs_normalised".to_string();
    for (i, (shape, weight, bias)) in layers.iter().enumerate() {
        let last = i + 1 == layers.len();
        // NOTE: the last layer gives the mean and the log-std; the mean action needs the
        // mean's rows alone.
        let rows = if last { act_dim } else { shape[0] };
        let (wn, bn) = (format!("pi.l{i}.weight"), format!("pi.l{i}.bias"));
        g.initializer.push(float_tensor(
            &wn,
            &[rows as i64, shape[1] as i64],
            &weight[..rows * shape[1]],
        ));
        g.initializer
            .push(float_tensor(&bn, &[rows as i64], &bias[..rows]));
        let out = if last {
            "mean".to_string()
        } else {
            format!("h{i}")
        };
        g.node.push(node(
            "Gemm",
            &[&h, &wn, &bn],
            &out,
            vec![int_attr("transB", 1)],
        ));
        h = out;
        if !last {
            let r = format!("h{i}_relu");
            g.node.push(node("Relu", &[&h], &r, vec![]));
            h = r;
        }
    }
    g.node.push(node("Tanh", &[&h], "action", vec![]));
    g.input.push(value_info(
        "obs",
        &[Dim::DimParam("N".into()), Dim::DimValue(obs_dim as i64)],
    ));
    g.output.push(value_info(
        "action",
        &[Dim::DimParam("N".into()), Dim::DimValue(act_dim as i64)],
    ));
    let mut m = ModelProto::new();
    m.ir_version = IR_VERSION;
    let mut opset = OperatorSetIdProto::new();
    opset.domain = String::new();
    opset.version = OPSET;
    m.opset_import.push(opset);
    m.producer_name = "pbrl".into();
    m.producer_version = env!("CARGO_PKG_VERSION").into();
    m.doc_string = doc.into();
    m.metadata_props = meta
        .iter()
        .map(|(k, v)| {
            let mut e = StringStringEntryProto::new();
            e.key = k.to_string();
            e.value = v.clone();
            e
        })
        .collect();
    m.graph = Some(g).into();
    Ok(m)
}

/// The card's path next to the model: `policy.onnx` -> `policy.card.json`.
pub fn card_path(onnx: &Path) -> PathBuf {
    onnx.with_extension("card.json")
}
