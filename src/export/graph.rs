//! ONNX graphs of a policy's networks, written with ONNX's own protobuf messages (as tract-onnx
//! exposes them). Every graph takes and gives values in the environment's units: observations
//! as the client sends them, actions within the bundle's bounds; the observation normalisation,
//! the action scaling and the model's residual and bounds are inside.

use tract_onnx::pb;
use tract_onnx::pb::attribute_proto::AttributeType;
use tract_onnx::pb::tensor_proto::DataType;

use crate::nn::{Activation, Dense, LAYER_NORM_EPS, LayerNorm, Mlp};

/// The operator set the graphs are written against: 17 brings LayerNormalization.
pub const OPSET: i64 = 17;
/// ONNX IR version 8 goes with opset 17 (ONNX 1.12 and later read it).
const IR_VERSION: i64 = 8;

/// The name of the batch dimension of every input and output.
const BATCH: &str = "batch";

/// A graph being built: nodes in order, constants as initializers, fresh value names.
pub(super) struct Graph {
    name: String,
    nodes: Vec<pb::NodeProto>,
    initializers: Vec<pb::TensorProto>,
    inputs: Vec<pb::ValueInfoProto>,
    outputs: Vec<pb::ValueInfoProto>,
    next: usize,
}

fn value_info(name: &str, width: usize) -> pb::ValueInfoProto {
    use pb::tensor_shape_proto::{Dimension, dimension::Value};
    let dims = [Value::DimParam(BATCH.into()), Value::DimValue(width as i64)];
    pb::ValueInfoProto {
        name: name.into(),
        r#type: Some(pb::TypeProto {
            denotation: String::new(),
            value: Some(pb::type_proto::Value::TensorType(pb::type_proto::Tensor {
                elem_type: DataType::Float as i32,
                shape: Some(pb::TensorShapeProto {
                    dim: dims
                        .into_iter()
                        .map(|v| Dimension {
                            denotation: String::new(),
                            value: Some(v),
                        })
                        .collect(),
                }),
            })),
        }),
        doc_string: String::new(),
    }
}

/// An attribute of one integer or one float.
pub(super) enum Attribute {
    Int(&'static str, i64),
    Float(&'static str, f32),
}

impl Graph {
    pub(super) fn new(name: &str) -> Graph {
        Graph {
            name: name.into(),
            nodes: Vec::new(),
            initializers: Vec::new(),
            inputs: Vec::new(),
            outputs: Vec::new(),
            next: 0,
        }
    }

    /// Declares an input of `width` floats per row.
    pub(super) fn input(&mut self, name: &str, width: usize) -> String {
        self.inputs.push(value_info(name, width));
        name.into()
    }

    /// Names `value` as an output of `width` floats per row.
    pub(super) fn output(&mut self, value: &str, name: &str, width: usize) {
        self.node("Identity", &[value], &[], Some(name));
        self.outputs.push(value_info(name, width));
    }

    fn fresh(&mut self, stem: &str) -> String {
        self.next += 1;
        format!("{stem}_{}", self.next)
    }

    /// A float constant of shape `dims` (row-major data).
    pub(super) fn constant(&mut self, stem: &str, dims: &[usize], data: &[f32]) -> String {
        debug_assert_eq!(dims.iter().product::<usize>(), data.len());
        let name = self.fresh(stem);
        self.initializers.push(pb::TensorProto {
            dims: dims.iter().map(|&d| d as i64).collect(),
            data_type: DataType::Float as i32,
            float_data: data.to_vec(),
            name: name.clone(),
            ..Default::default()
        });
        name
    }

    /// A scalar float constant.
    pub(super) fn scalar(&mut self, stem: &str, value: f32) -> String {
        self.constant(stem, &[], &[value])
    }

    /// A node of `op` over `inputs`; returns its output's name (`output` where given).
    pub(super) fn node(
        &mut self,
        op: &str,
        inputs: &[&str],
        attributes: &[Attribute],
        output: Option<&str>,
    ) -> String {
        let out = output.map_or_else(|| self.fresh(&op.to_lowercase()), str::to_string);
        let attribute = attributes
            .iter()
            .map(|a| match *a {
                Attribute::Int(name, i) => pb::AttributeProto {
                    name: name.into(),
                    r#type: AttributeType::Int as i32,
                    i,
                    ..Default::default()
                },
                Attribute::Float(name, f) => pb::AttributeProto {
                    name: name.into(),
                    r#type: AttributeType::Float as i32,
                    f,
                    ..Default::default()
                },
            })
            .collect();
        let name = self.fresh(op);
        self.nodes.push(pb::NodeProto {
            input: inputs.iter().map(|s| s.to_string()).collect(),
            output: vec![out.clone()],
            name,
            op_type: op.into(),
            domain: String::new(),
            attribute,
            doc_string: String::new(),
        });
        out
    }

    /// `x` through one affine layer: Gemm with the PyTorch-layout weight ([out, in]) transposed.
    pub(super) fn dense(&mut self, x: &str, layer: &Dense) -> String {
        let (out, inp) = (layer.output_dim(), layer.input_dim());
        let weight = self.constant("weight", &[out, inp], &layer.weight_row_major());
        let bias = self.constant("bias", &[out], layer.bias().as_slice());
        self.node(
            "Gemm",
            &[x, &weight, &bias],
            &[Attribute::Int("transB", 1)],
            None,
        )
    }

    fn layer_norm(&mut self, x: &str, norm: &LayerNorm) -> String {
        let scale = self.constant("ln_scale", &[norm.dim()], norm.scale());
        let shift = self.constant("ln_shift", &[norm.dim()], norm.shift());
        self.node(
            "LayerNormalization",
            &[x, &scale, &shift],
            &[
                Attribute::Int("axis", -1),
                Attribute::Float("epsilon", LAYER_NORM_EPS),
            ],
            None,
        )
    }

    fn activate(&mut self, x: &str, activation: Activation) -> String {
        let op = match activation {
            Activation::Relu => "Relu",
            Activation::Tanh => "Tanh",
        };
        self.node(op, &[x], &[], None)
    }

    /// `x` through a chain: each hidden layer normalised (where it has norms) then activated,
    /// the last activated only where the chain says so.
    pub(super) fn mlp(&mut self, x: &str, mlp: &Mlp) -> String {
        let mut value = x.to_string();
        let last = mlp.layers().len() - 1;
        for (i, layer) in mlp.layers().iter().enumerate() {
            value = self.dense(&value, layer);
            if i < last {
                if let Some(norm) = mlp.norms().get(i) {
                    value = self.layer_norm(&value, norm);
                }
                value = self.activate(&value, mlp.activation());
            } else if mlp.activates_output() {
                value = self.activate(&value, mlp.activation());
            }
        }
        value
    }

    /// `clip(x, lo, hi)` with scalar bounds.
    pub(super) fn clip(&mut self, x: &str, lo: f32, hi: f32) -> String {
        let (lo, hi) = (self.scalar("lo", lo), self.scalar("hi", hi));
        self.node("Clip", &[x, &lo, &hi], &[], None)
    }

    /// `op(x, constant)` with a per-feature constant row.
    pub(super) fn with_row(&mut self, op: &str, x: &str, stem: &str, row: &[f32]) -> String {
        let c = self.constant(stem, &[row.len()], row);
        self.node(op, &[x, &c], &[], None)
    }

    /// `op(x, constant)` with a scalar constant.
    pub(super) fn with_scalar(&mut self, op: &str, x: &str, stem: &str, value: f32) -> String {
        let c = self.scalar(stem, value);
        self.node(op, &[x, &c], &[], None)
    }

    /// The model file's bytes: `doc` says what the graph computes.
    pub(super) fn into_model(self, doc: &str) -> pb::ModelProto {
        pb::ModelProto {
            ir_version: IR_VERSION,
            opset_import: vec![pb::OperatorSetIdProto {
                domain: String::new(),
                version: OPSET,
            }],
            producer_name: "prac".into(),
            producer_version: env!("CARGO_PKG_VERSION").into(),
            doc_string: doc.into(),
            graph: Some(pb::GraphProto {
                node: self.nodes,
                name: self.name,
                initializer: self.initializers,
                input: self.inputs,
                output: self.outputs,
                ..Default::default()
            }),
            ..Default::default()
        }
    }
}
