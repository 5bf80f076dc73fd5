//! A small graph builder on top of [`super::proto`]: named values, weights as initializers,
//! and the handful of layers the pir2 models need (linear, conv, group norm, Mish, …),
//! all in the default ONNX domain at opset [`OPSET`].

use super::proto::{
    AttrValue, Attribute, DataType, Dim, GraphProto, ModelProto, NodeProto, TensorProto,
    ValueInfoProto,
};

/// The default-domain opset the exporter targets.
pub const OPSET: i64 = 17;
/// The IR version that goes with [`OPSET`].
pub const IR_VERSION: i64 = 8;

/// Builds one ONNX graph. Values are referred to by name (`String`).
#[derive(Debug, Default)]
pub struct GraphBuilder {
    graph: GraphProto,
    counter: usize,
}

/// Shorthand for building attribute lists.
pub fn attr(name: &str, value: AttrValue) -> Attribute {
    Attribute {
        name: name.to_string(),
        value,
    }
}

impl GraphBuilder {
    /// An empty graph.
    pub fn new(name: &str) -> Self {
        GraphBuilder {
            graph: GraphProto {
                name: name.to_string(),
                ..GraphProto::default()
            },
            counter: 0,
        }
    }

    fn fresh(&mut self, hint: &str) -> String {
        self.counter += 1;
        format!("{hint}_{}", self.counter)
    }

    /// Declare a graph input.
    pub fn input(&mut self, name: &str, elem_type: DataType, shape: Vec<Dim>) -> String {
        self.graph.inputs.push(ValueInfoProto {
            name: name.to_string(),
            elem_type,
            shape,
        });
        name.to_string()
    }

    /// Declare `value` as a graph output called `name` (adds an `Identity` if the names differ).
    pub fn output(&mut self, value: &str, name: &str, elem_type: DataType, shape: Vec<Dim>) {
        if value != name {
            self.node_named("Identity", &[value], vec![], name);
        }
        self.graph.outputs.push(ValueInfoProto {
            name: name.to_string(),
            elem_type,
            shape,
        });
    }

    /// Add an `f32` initializer (a weight); returns its name.
    pub fn weight(&mut self, name: &str, dims: &[usize], data: &[f32]) -> String {
        let name = if self.graph.initializers.iter().any(|t| t.name == name) {
            self.fresh(name)
        } else {
            name.to_string()
        };
        self.graph
            .initializers
            .push(TensorProto::f32(name.clone(), dims, data));
        name
    }

    /// Add an `f32` constant with a generated name.
    pub fn const_f32(&mut self, dims: &[usize], data: &[f32]) -> String {
        let name = self.fresh("const");
        self.graph
            .initializers
            .push(TensorProto::f32(name.clone(), dims, data));
        name
    }

    /// Add an `i64` constant (shapes, axes) with a generated name.
    pub fn const_i64(&mut self, data: &[i64]) -> String {
        let name = self.fresh("shape");
        self.graph
            .initializers
            .push(TensorProto::i64(name.clone(), &[data.len()], data));
        name
    }

    /// Add a scalar `i64` constant.
    pub fn const_i64_scalar(&mut self, v: i64) -> String {
        let name = self.fresh("int");
        self.graph
            .initializers
            .push(TensorProto::i64(name.clone(), &[], &[v]));
        name
    }

    fn node_named(&mut self, op: &str, inputs: &[&str], attributes: Vec<Attribute>, out: &str) {
        let name = self.fresh(op);
        self.graph.nodes.push(NodeProto {
            op_type: op.to_string(),
            name,
            inputs: inputs.iter().map(|s| s.to_string()).collect(),
            outputs: vec![out.to_string()],
            attributes,
        });
    }

    /// Apply an operator with one output; returns the output name.
    pub fn op(&mut self, op: &str, inputs: &[&str], attributes: Vec<Attribute>) -> String {
        let out = self.fresh(&op.to_ascii_lowercase());
        self.node_named(op, inputs, attributes, &out);
        out
    }

    // ---- elementwise ----

    /// `a + b` (broadcasting).
    pub fn add(&mut self, a: &str, b: &str) -> String {
        self.op("Add", &[a, b], vec![])
    }
    /// `a - b` (broadcasting).
    pub fn sub(&mut self, a: &str, b: &str) -> String {
        self.op("Sub", &[a, b], vec![])
    }
    /// `a * b` (broadcasting).
    pub fn mul(&mut self, a: &str, b: &str) -> String {
        self.op("Mul", &[a, b], vec![])
    }
    /// `a / b` (broadcasting).
    pub fn div(&mut self, a: &str, b: &str) -> String {
        self.op("Div", &[a, b], vec![])
    }
    /// `x * scalar`.
    pub fn scale(&mut self, x: &str, s: f32) -> String {
        let c = self.const_f32(&[], &[s]);
        self.mul(x, &c)
    }
    /// `x + scalar`.
    pub fn offset(&mut self, x: &str, s: f32) -> String {
        let c = self.const_f32(&[], &[s]);
        self.add(x, &c)
    }
    /// Unary operator by name (`"Sin"`, `"Cos"`, `"Relu"`, `"Tanh"`, `"Sigmoid"`, `"Exp"`, …).
    pub fn unary(&mut self, op: &str, x: &str) -> String {
        self.op(op, &[x], vec![])
    }
    /// Mish: `x · tanh(softplus(x))` (opset 17 has no `Mish`).
    pub fn mish(&mut self, x: &str) -> String {
        let sp = self.unary("Softplus", x);
        let t = self.unary("Tanh", &sp);
        self.mul(x, &t)
    }
    /// SiLU: `x · sigmoid(x)`.
    pub fn silu(&mut self, x: &str) -> String {
        let s = self.unary("Sigmoid", x);
        self.mul(x, &s)
    }
    /// GELU, erf form: `0.5·x·(1 + erf(x/√2))`.
    pub fn gelu_erf(&mut self, x: &str) -> String {
        let a = self.scale(x, std::f32::consts::FRAC_1_SQRT_2);
        let e = self.unary("Erf", &a);
        let e1 = self.offset(&e, 1.0);
        let h = self.scale(x, 0.5);
        self.mul(&h, &e1)
    }
    /// GELU, tanh approximation: `0.5·x·(1 + tanh(√(2/π)·(x + 0.044715·x³)))`.
    pub fn gelu_tanh(&mut self, x: &str) -> String {
        let x2 = self.mul(x, x);
        let x3 = self.mul(&x2, x);
        let c = self.scale(&x3, 0.044715);
        let inner = self.add(x, &c);
        let s = self.scale(&inner, (2.0 / std::f32::consts::PI).sqrt());
        let t = self.unary("Tanh", &s);
        let t1 = self.offset(&t, 1.0);
        let h = self.scale(x, 0.5);
        self.mul(&h, &t1)
    }

    // ---- shapes ----

    /// `Reshape` (`0` copies the input dimension, `-1` infers).
    pub fn reshape(&mut self, x: &str, shape: &[i64]) -> String {
        let s = self.const_i64(shape);
        self.op("Reshape", &[x, &s], vec![])
    }
    /// `Transpose` with a permutation.
    pub fn transpose(&mut self, x: &str, perm: &[i64]) -> String {
        self.op(
            "Transpose",
            &[x],
            vec![attr("perm", AttrValue::Ints(perm.to_vec()))],
        )
    }
    /// `Concat` along `axis`.
    pub fn concat(&mut self, xs: &[&str], axis: i64) -> String {
        self.op("Concat", xs, vec![attr("axis", AttrValue::Int(axis))])
    }
    /// `Unsqueeze` at `axes`.
    pub fn unsqueeze(&mut self, x: &str, axes: &[i64]) -> String {
        let a = self.const_i64(axes);
        self.op("Unsqueeze", &[x, &a], vec![])
    }
    /// `Slice` along one axis: `[start, end)`.
    pub fn slice(&mut self, x: &str, axis: i64, start: i64, end: i64) -> String {
        let s = self.const_i64(&[start]);
        let e = self.const_i64(&[end]);
        let a = self.const_i64(&[axis]);
        self.op("Slice", &[x, &s, &e, &a], vec![])
    }
    /// `Cast` to `f32`.
    pub fn cast_f32(&mut self, x: &str) -> String {
        self.op(
            "Cast",
            &[x],
            vec![attr("to", AttrValue::Int(DataType::Float as i64))],
        )
    }

    // ---- layers ----

    /// A linear layer on the last axis, candle/PyTorch convention: `y = x·Wᵀ + b` with `w`
    /// given as `[out, in]` row-major. The weight is stored pre-transposed (`[in, out]`) so the
    /// graph is a single `MatMul` (+ `Add`).
    pub fn linear(
        &mut self,
        x: &str,
        name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        in_dim: usize,
        out_dim: usize,
    ) -> String {
        debug_assert_eq!(w.len(), in_dim * out_dim, "linear `{name}`: weight length");
        let mut wt = vec![0f32; w.len()];
        for o in 0..out_dim {
            for i in 0..in_dim {
                wt[i * out_dim + o] = w[o * in_dim + i];
            }
        }
        let wn = self.weight(&format!("{name}.weight_t"), &[in_dim, out_dim], &wt);
        let y = self.op("MatMul", &[x, &wn], vec![]);
        match b {
            Some(b) => {
                debug_assert_eq!(b.len(), out_dim, "linear `{name}`: bias length");
                let bn = self.weight(&format!("{name}.bias"), &[out_dim], b);
                self.add(&y, &bn)
            }
            None => y,
        }
    }

    /// 1-D convolution on `[B, C_in, L]`, weight `[C_out, C_in, K]`, symmetric zero padding.
    #[allow(clippy::too_many_arguments)]
    pub fn conv1d(
        &mut self,
        x: &str,
        name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        pad: usize,
    ) -> String {
        debug_assert_eq!(w.len(), c_out * c_in * k, "conv1d `{name}`: weight length");
        let wn = self.weight(&format!("{name}.weight"), &[c_out, c_in, k], w);
        let mut inputs = vec![x.to_string(), wn];
        if let Some(b) = b {
            debug_assert_eq!(b.len(), c_out, "conv1d `{name}`: bias length");
            inputs.push(self.weight(&format!("{name}.bias"), &[c_out], b));
        }
        let refs: Vec<&str> = inputs.iter().map(String::as_str).collect();
        self.op(
            "Conv",
            &refs,
            vec![
                attr("kernel_shape", AttrValue::Ints(vec![k as i64])),
                attr("strides", AttrValue::Ints(vec![stride as i64])),
                attr("pads", AttrValue::Ints(vec![pad as i64, pad as i64])),
            ],
        )
    }

    /// 1-D transposed convolution on `[B, C_in, L]`, weight `[C_in, C_out, K]` (PyTorch layout).
    #[allow(clippy::too_many_arguments)]
    pub fn conv_transpose1d(
        &mut self,
        x: &str,
        name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        pad: usize,
        output_padding: usize,
    ) -> String {
        debug_assert_eq!(
            w.len(),
            c_out * c_in * k,
            "conv_transpose1d `{name}`: weight length"
        );
        let wn = self.weight(&format!("{name}.weight"), &[c_in, c_out, k], w);
        let mut inputs = vec![x.to_string(), wn];
        if let Some(b) = b {
            debug_assert_eq!(b.len(), c_out, "conv_transpose1d `{name}`: bias length");
            inputs.push(self.weight(&format!("{name}.bias"), &[c_out], b));
        }
        let refs: Vec<&str> = inputs.iter().map(String::as_str).collect();
        self.op(
            "ConvTranspose",
            &refs,
            vec![
                attr("kernel_shape", AttrValue::Ints(vec![k as i64])),
                attr("strides", AttrValue::Ints(vec![stride as i64])),
                attr("pads", AttrValue::Ints(vec![pad as i64, pad as i64])),
                attr(
                    "output_padding",
                    AttrValue::Ints(vec![output_padding as i64]),
                ),
            ],
        )
    }

    /// Group normalisation of `[B, C, L]` with `groups` groups and per-channel affine
    /// `gamma`, `beta` (`[C]`). Opset 17 has no `GroupNormalization`, so this is the standard
    /// decomposition: reshape to `[B, G, C/G·L]`, `InstanceNormalization` (unit scale, zero
    /// bias), reshape back, then the per-channel affine.
    #[allow(clippy::too_many_arguments)]
    pub fn group_norm(
        &mut self,
        x: &str,
        name: &str,
        gamma: &[f32],
        beta: &[f32],
        channels: usize,
        groups: usize,
        eps: f32,
    ) -> String {
        debug_assert_eq!(
            channels % groups,
            0,
            "group_norm `{name}`: {channels} channels not divisible by {groups} groups"
        );
        debug_assert_eq!(gamma.len(), channels);
        debug_assert_eq!(beta.len(), channels);
        let g = self.reshape(x, &[0, groups as i64, -1]);
        let ones = self.const_f32(&[groups], &vec![1.0; groups]);
        let zeros = self.const_f32(&[groups], &vec![0.0; groups]);
        let n = self.op(
            "InstanceNormalization",
            &[&g, &ones, &zeros],
            vec![attr("epsilon", AttrValue::Float(eps))],
        );
        // Back to [B, C, L]: L is recovered from the input's shape.
        let shape = self.op("Shape", &[x], vec![]);
        let back = self.op("Reshape", &[&n, &shape], vec![]);
        let gn = self.weight(&format!("{name}.weight"), &[channels, 1], gamma);
        let bn = self.weight(&format!("{name}.bias"), &[channels, 1], beta);
        let s = self.mul(&back, &gn);
        self.add(&s, &bn)
    }

    /// Layer normalisation over the last axis (`LayerNormalization`, opset 17).
    pub fn layer_norm(
        &mut self,
        x: &str,
        name: &str,
        gamma: &[f32],
        beta: Option<&[f32]>,
        eps: f32,
    ) -> String {
        let d = gamma.len();
        let gn = self.weight(&format!("{name}.weight"), &[d], gamma);
        let mut inputs = vec![x.to_string(), gn];
        if let Some(b) = beta {
            inputs.push(self.weight(&format!("{name}.bias"), &[d], b));
        }
        let refs: Vec<&str> = inputs.iter().map(String::as_str).collect();
        self.op(
            "LayerNormalization",
            &refs,
            vec![
                attr("axis", AttrValue::Int(-1)),
                attr("epsilon", AttrValue::Float(eps)),
            ],
        )
    }

    /// Finish the graph into a model with the given metadata.
    pub fn finish(self, metadata: Vec<(String, String)>) -> ModelProto {
        ModelProto {
            ir_version: IR_VERSION,
            opset: OPSET,
            producer_name: "pir2".to_string(),
            producer_version: env!("CARGO_PKG_VERSION").to_string(),
            graph: self.graph,
            metadata,
        }
    }
}
