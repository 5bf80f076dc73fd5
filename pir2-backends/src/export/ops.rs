//! The op vocabulary the exported models are written in, so one model definition serves
//! every export target: [`GraphBuilder`] emits ONNX nodes, and (feature `tch`)
//! `crate::tch::TchOps` applies libtorch ops while a closure is traced into TorchScript.
//!
//! Conventions: the batch axis is always first and is never named in a shape (reshapes use
//! `-1` for it); linear weights are `[out, in]`, conv weights `[C_out, C_in, K]`, transposed
//! conv weights `[C_in, C_out, K]` (PyTorch/candle layouts).

use super::graph::GraphBuilder;
use crate::error::{Error, Result};

/// Element-wise unary functions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unary {
    /// `sin`.
    Sin,
    /// `cos`.
    Cos,
    /// `exp`.
    Exp,
    /// `tanh`.
    Tanh,
    /// `sigmoid`.
    Sigmoid,
    /// `max(x, 0)`.
    Relu,
    /// `ln(1 + eˣ)`.
    Softplus,
}

/// A tensor-op sink: ONNX graph builder or libtorch tracer.
pub trait Ops {
    /// A tensor value.
    type T: Clone;

    /// A constant `f32` tensor (weights, tables).
    fn constant(&mut self, name: &str, shape: &[usize], data: &[f32]) -> Self::T;
    /// `x·Wᵀ + b` on the last axis, `w` is `[out, in]`.
    fn linear(
        &mut self,
        x: &Self::T,
        name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        in_dim: usize,
        out_dim: usize,
    ) -> Self::T;
    /// 1-D convolution of `[B, C_in, L]`.
    #[allow(clippy::too_many_arguments)]
    fn conv1d(
        &mut self,
        x: &Self::T,
        name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        pad: usize,
    ) -> Self::T;
    /// 1-D transposed convolution of `[B, C_in, L]`.
    #[allow(clippy::too_many_arguments)]
    fn conv_transpose1d(
        &mut self,
        x: &Self::T,
        name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        pad: usize,
        output_padding: usize,
    ) -> Self::T;
    /// Group normalisation of `[B, C, L]` with per-channel affine.
    #[allow(clippy::too_many_arguments)]
    fn group_norm(
        &mut self,
        x: &Self::T,
        name: &str,
        gamma: &[f32],
        beta: &[f32],
        channels: usize,
        groups: usize,
        eps: f32,
    ) -> Self::T;
    /// `a + b` (broadcasting).
    fn add(&mut self, a: &Self::T, b: &Self::T) -> Self::T;
    /// `a − b` (broadcasting).
    fn sub(&mut self, a: &Self::T, b: &Self::T) -> Self::T;
    /// `a · b` (broadcasting).
    fn mul(&mut self, a: &Self::T, b: &Self::T) -> Self::T;
    /// `a / b` (broadcasting).
    fn div(&mut self, a: &Self::T, b: &Self::T) -> Self::T;
    /// `1.0` where `x < 0`, else `0.0`.
    fn is_negative(&mut self, x: &Self::T) -> Self::T;
    /// `min(x, s)`.
    fn min_scalar(&mut self, x: &Self::T, s: f32) -> Self::T;
    /// Embedding lookup: `ids` (int64 `[B]`) clamped to `[0, rows − 1]`, rows of `table`
    /// (`[rows, dim]`) → `[B, dim]`.
    fn embedding(
        &mut self,
        ids: &Self::T,
        name: &str,
        table: &[f32],
        rows: usize,
        dim: usize,
    ) -> Self::T;
    /// Mean over `axis` (the axis is removed).
    fn mean(&mut self, x: &Self::T, axis: i64) -> Self::T;
    /// `x · s`.
    fn scale(&mut self, x: &Self::T, s: f32) -> Self::T;
    /// `x + s`.
    fn offset(&mut self, x: &Self::T, s: f32) -> Self::T;
    /// An element-wise function.
    fn unary(&mut self, f: Unary, x: &Self::T) -> Self::T;
    /// Concatenate along `axis` (negative counts from the end).
    fn concat(&mut self, xs: &[Self::T], axis: i64) -> Self::T;
    /// Reshape; `-1` (once) is inferred. The batch is always `-1` or folded into a `-1`.
    fn reshape(&mut self, x: &Self::T, shape: &[i64]) -> Self::T;
    /// Permute axes.
    fn transpose(&mut self, x: &Self::T, perm: &[i64]) -> Self::T;
    /// Insert a unit axis at `axis`.
    fn unsqueeze(&mut self, x: &Self::T, axis: i64) -> Self::T;
    /// `x[..., start..end, ...]` along `axis`.
    fn slice(&mut self, x: &Self::T, axis: i64, start: i64, end: i64) -> Self::T;
    /// Cast an integer tensor to `f32`.
    fn to_f32(&mut self, x: &Self::T) -> Self::T;

    /// Mish: `x · tanh(softplus(x))`.
    fn mish(&mut self, x: &Self::T) -> Self::T {
        let sp = self.unary(Unary::Softplus, x);
        let t = self.unary(Unary::Tanh, &sp);
        self.mul(x, &t)
    }
    /// SiLU: `x · sigmoid(x)`.
    fn silu(&mut self, x: &Self::T) -> Self::T {
        let s = self.unary(Unary::Sigmoid, x);
        self.mul(x, &s)
    }
}

impl Ops for GraphBuilder {
    type T = String;

    fn constant(&mut self, name: &str, shape: &[usize], data: &[f32]) -> String {
        self.weight(name, shape, data)
    }
    fn linear(
        &mut self,
        x: &String,
        name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        in_dim: usize,
        out_dim: usize,
    ) -> String {
        GraphBuilder::linear(self, x, name, w, b, in_dim, out_dim)
    }
    fn conv1d(
        &mut self,
        x: &String,
        name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        pad: usize,
    ) -> String {
        GraphBuilder::conv1d(self, x, name, w, b, c_in, c_out, k, stride, pad)
    }
    fn conv_transpose1d(
        &mut self,
        x: &String,
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
        GraphBuilder::conv_transpose1d(
            self,
            x,
            name,
            w,
            b,
            c_in,
            c_out,
            k,
            stride,
            pad,
            output_padding,
        )
    }
    fn group_norm(
        &mut self,
        x: &String,
        name: &str,
        gamma: &[f32],
        beta: &[f32],
        channels: usize,
        groups: usize,
        eps: f32,
    ) -> String {
        GraphBuilder::group_norm(self, x, name, gamma, beta, channels, groups, eps)
    }
    fn add(&mut self, a: &String, b: &String) -> String {
        GraphBuilder::add(self, a, b)
    }
    fn sub(&mut self, a: &String, b: &String) -> String {
        GraphBuilder::sub(self, a, b)
    }
    fn mul(&mut self, a: &String, b: &String) -> String {
        GraphBuilder::mul(self, a, b)
    }
    fn div(&mut self, a: &String, b: &String) -> String {
        GraphBuilder::div(self, a, b)
    }
    fn is_negative(&mut self, x: &String) -> String {
        let z = self.const_f32(&[], &[0.0]);
        let m = self.op("Less", &[x, &z], vec![]);
        self.cast_f32(&m)
    }
    fn min_scalar(&mut self, x: &String, s: f32) -> String {
        let c = self.const_f32(&[], &[s]);
        self.op("Min", &[x, &c], vec![])
    }
    fn embedding(
        &mut self,
        ids: &String,
        name: &str,
        table: &[f32],
        rows: usize,
        dim: usize,
    ) -> String {
        let t = self.weight(name, &[rows, dim], table);
        let lo = self.const_i64_scalar(0);
        let hi = self.const_i64_scalar(rows as i64 - 1);
        let c = self.op("Clip", &[ids, &lo, &hi], vec![]);
        self.op(
            "Gather",
            &[&t, &c],
            vec![super::graph::attr("axis", super::proto::AttrValue::Int(0))],
        )
    }
    fn mean(&mut self, x: &String, axis: i64) -> String {
        use super::graph::attr;
        use super::proto::AttrValue;
        // Opset 17: `axes` is an attribute.
        self.op(
            "ReduceMean",
            &[x],
            vec![
                attr("axes", AttrValue::Ints(vec![axis])),
                attr("keepdims", AttrValue::Int(0)),
            ],
        )
    }
    fn scale(&mut self, x: &String, s: f32) -> String {
        GraphBuilder::scale(self, x, s)
    }
    fn offset(&mut self, x: &String, s: f32) -> String {
        GraphBuilder::offset(self, x, s)
    }
    fn unary(&mut self, f: Unary, x: &String) -> String {
        let op = match f {
            Unary::Sin => "Sin",
            Unary::Cos => "Cos",
            Unary::Exp => "Exp",
            Unary::Tanh => "Tanh",
            Unary::Sigmoid => "Sigmoid",
            Unary::Relu => "Relu",
            Unary::Softplus => "Softplus",
        };
        GraphBuilder::unary(self, op, x)
    }
    fn concat(&mut self, xs: &[String], axis: i64) -> String {
        let refs: Vec<&str> = xs.iter().map(String::as_str).collect();
        GraphBuilder::concat(self, &refs, axis)
    }
    fn reshape(&mut self, x: &String, shape: &[i64]) -> String {
        GraphBuilder::reshape(self, x, shape)
    }
    fn transpose(&mut self, x: &String, perm: &[i64]) -> String {
        GraphBuilder::transpose(self, x, perm)
    }
    fn unsqueeze(&mut self, x: &String, axis: i64) -> String {
        GraphBuilder::unsqueeze(self, x, &[axis])
    }
    fn slice(&mut self, x: &String, axis: i64, start: i64, end: i64) -> String {
        GraphBuilder::slice(self, x, axis, start, end)
    }
    fn to_f32(&mut self, x: &String) -> String {
        self.cast_f32(x)
    }
}

/// Named weights with shapes, the exporter's view of a checkpoint.
pub trait WeightSource {
    /// The weight `name`, checked to have exactly `shape`.
    fn weight(&self, model: &'static str, name: &str, shape: &[usize]) -> Result<Vec<f32>>;
}

/// A simple in-memory [`WeightSource`]: name → (shape, row-major data).
#[derive(Debug, Clone, Default)]
pub struct NamedWeights {
    map: std::collections::BTreeMap<String, (Vec<usize>, Vec<f32>)>,
}

impl NamedWeights {
    /// Empty.
    pub fn new() -> Self {
        Self::default()
    }
    /// Insert (or replace) a weight.
    pub fn insert(&mut self, name: impl Into<String>, shape: Vec<usize>, data: Vec<f32>) {
        self.map.insert(name.into(), (shape, data));
    }
    /// Iterate over `(name, shape, data)`.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &[usize], &[f32])> {
        self.map
            .iter()
            .map(|(k, (s, d))| (k.as_str(), s.as_slice(), d.as_slice()))
    }
    /// Random weights for the given `(name, shape)` list (tests, benches): matrices and
    /// kernels `U(±1/√fan_in)`, norm scales `1 + U(±0.1)`, biases `U(±0.1)`. Deterministic in `seed`.
    pub fn random(shapes: &[(String, Vec<usize>)], seed: u64) -> Self {
        let mut rng = pir2_schedule::Rng::new(seed);
        let mut w = NamedWeights::new();
        for (name, shape) in shapes {
            let n: usize = shape.iter().product();
            let data: Vec<f32> = if shape.len() >= 2 {
                let fan_in: usize = shape[1..].iter().product();
                let s = 1.0 / (fan_in.max(1) as f32).sqrt();
                (0..n).map(|_| rng.uniform_range(-s, s)).collect()
            } else if name.contains("norm.weight") {
                (0..n).map(|_| 1.0 + rng.uniform_range(-0.1, 0.1)).collect()
            } else {
                (0..n).map(|_| rng.uniform_range(-0.1, 0.1)).collect()
            };
            w.insert(name.clone(), shape.clone(), data);
        }
        w
    }

    /// Number of weights.
    pub fn len(&self) -> usize {
        self.map.len()
    }
    /// No weights?
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }
}

impl WeightSource for NamedWeights {
    fn weight(&self, model: &'static str, name: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let (s, d) = self.map.get(name).ok_or_else(|| Error::MissingWeight {
            model,
            name: name.to_string(),
        })?;
        if s.as_slice() != shape {
            return Err(Error::WeightShape {
                model,
                name: name.to_string(),
                expected: shape.to_vec(),
                got: s.clone(),
            });
        }
        Ok(d.clone())
    }
}
