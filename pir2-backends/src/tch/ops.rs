//! [`Ops`] on libtorch tensors: run a model definition eagerly, or inside
//! [`tch::CModule::create_by_tracing`] to turn it into TorchScript (weights become constants
//! of the traced graph). Shapes never read the batch size, so traced modules stay
//! batch-agnostic.

use ::tch::{Kind, Tensor};

use crate::export::ops::{Ops, Unary};

/// A libtorch tensor with a cheap (reference-sharing) `Clone`.
#[derive(Debug)]
pub struct TchValue(pub Tensor);

impl Clone for TchValue {
    fn clone(&self) -> Self {
        TchValue(self.0.shallow_clone())
    }
}

/// The libtorch op sink.
///
/// Constant tensors must not be created while a trace is recording: libtorch would record
/// the allocation (`aten::empty`) but not the copy of the data, and the traced module would
/// read uninitialised memory. So [`TchOps::record`] runs the definition once eagerly and keeps
/// every constant in creation order, and [`TchOps::replay`] hands the same tensors out again
/// inside the trace (where they become constants of the graph).
#[derive(Debug, Default)]
pub struct TchOps {
    constants: Vec<Tensor>,
    replay: Option<usize>,
}

impl TchOps {
    /// Eager mode: constants are created (and remembered).
    pub fn record() -> Self {
        TchOps {
            constants: Vec::new(),
            replay: None,
        }
    }

    /// Replay mode: constants come from a previous [`TchOps::record`] run, in order.
    pub fn replay(recorded: TchOps) -> Self {
        TchOps {
            constants: recorded.constants,
            replay: Some(0),
        }
    }

    fn t(&mut self, data: &[f32], shape: &[usize]) -> Tensor {
        match &mut self.replay {
            Some(i) if *i < self.constants.len() => {
                let t = self.constants[*i].shallow_clone();
                *i += 1;
                t
            }
            _ => {
                let s: Vec<i64> = shape.iter().map(|&d| d as i64).collect();
                let t = Tensor::from_slice(data).reshape(&s[..]);
                if self.replay.is_none() {
                    self.constants.push(t.shallow_clone());
                }
                t
            }
        }
    }

    fn scalar(&mut self, s: f32) -> Tensor {
        self.t(&[s], &[])
    }
}

impl Ops for TchOps {
    type T = TchValue;

    fn constant(&mut self, _name: &str, shape: &[usize], data: &[f32]) -> TchValue {
        TchValue(self.t(data, shape))
    }
    fn linear(
        &mut self,
        x: &TchValue,
        _name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        in_dim: usize,
        out_dim: usize,
    ) -> TchValue {
        let w = self.t(w, &[out_dim, in_dim]);
        let b = b.map(|b| self.t(b, &[out_dim]));
        TchValue(x.0.linear(&w, b.as_ref()))
    }
    fn conv1d(
        &mut self,
        x: &TchValue,
        _name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        pad: usize,
    ) -> TchValue {
        let w = self.t(w, &[c_out, c_in, k]);
        let b = b.map(|b| self.t(b, &[c_out]));
        TchValue(x.0.conv1d(&w, b.as_ref(), [stride as i64], [pad as i64], [1], 1))
    }
    fn conv_transpose1d(
        &mut self,
        x: &TchValue,
        _name: &str,
        w: &[f32],
        b: Option<&[f32]>,
        c_in: usize,
        c_out: usize,
        k: usize,
        stride: usize,
        pad: usize,
        output_padding: usize,
    ) -> TchValue {
        let w = self.t(w, &[c_in, c_out, k]);
        let b = b.map(|b| self.t(b, &[c_out]));
        TchValue(x.0.conv_transpose1d(
            &w,
            b.as_ref(),
            [stride as i64],
            [pad as i64],
            [output_padding as i64],
            1,
            [1],
        ))
    }
    fn group_norm(
        &mut self,
        x: &TchValue,
        _name: &str,
        gamma: &[f32],
        beta: &[f32],
        channels: usize,
        groups: usize,
        eps: f32,
    ) -> TchValue {
        let g = self.t(gamma, &[channels]);
        let b = self.t(beta, &[channels]);
        TchValue(x.0.group_norm(groups as i64, Some(&g), Some(&b), f64::from(eps), false))
    }
    fn add(&mut self, a: &TchValue, b: &TchValue) -> TchValue {
        TchValue(&a.0 + &b.0)
    }
    fn sub(&mut self, a: &TchValue, b: &TchValue) -> TchValue {
        TchValue(&a.0 - &b.0)
    }
    fn mul(&mut self, a: &TchValue, b: &TchValue) -> TchValue {
        TchValue(&a.0 * &b.0)
    }
    fn div(&mut self, a: &TchValue, b: &TchValue) -> TchValue {
        TchValue(&a.0 / &b.0)
    }
    fn is_negative(&mut self, x: &TchValue) -> TchValue {
        TchValue(x.0.lt(0.0).to_kind(Kind::Float))
    }
    fn min_scalar(&mut self, x: &TchValue, s: f32) -> TchValue {
        TchValue(x.0.minimum(&self.scalar(s)))
    }
    fn embedding(
        &mut self,
        ids: &TchValue,
        _name: &str,
        table: &[f32],
        rows: usize,
        dim: usize,
    ) -> TchValue {
        let t = self.t(table, &[rows, dim]);
        let c = ids.0.clamp(0, rows as i64 - 1);
        TchValue(t.index_select(0, &c))
    }
    fn mean(&mut self, x: &TchValue, axis: i64) -> TchValue {
        TchValue(x.0.mean_dim(&[axis][..], false, Kind::Float))
    }
    fn scale(&mut self, x: &TchValue, s: f32) -> TchValue {
        TchValue(&x.0 * self.scalar(s))
    }
    fn offset(&mut self, x: &TchValue, s: f32) -> TchValue {
        TchValue(&x.0 + self.scalar(s))
    }
    fn unary(&mut self, f: Unary, x: &TchValue) -> TchValue {
        let x = &x.0;
        TchValue(match f {
            Unary::Sin => x.sin(),
            Unary::Cos => x.cos(),
            Unary::Exp => x.exp(),
            Unary::Tanh => x.tanh(),
            Unary::Sigmoid => x.sigmoid(),
            Unary::Relu => x.relu(),
            Unary::Softplus => x.softplus(),
        })
    }
    fn concat(&mut self, xs: &[TchValue], axis: i64) -> TchValue {
        let ts: Vec<&Tensor> = xs.iter().map(|v| &v.0).collect();
        TchValue(Tensor::cat(&ts, axis))
    }
    fn reshape(&mut self, x: &TchValue, shape: &[i64]) -> TchValue {
        TchValue(x.0.reshape(shape))
    }
    fn transpose(&mut self, x: &TchValue, perm: &[i64]) -> TchValue {
        TchValue(x.0.permute(perm))
    }
    fn unsqueeze(&mut self, x: &TchValue, axis: i64) -> TchValue {
        TchValue(x.0.unsqueeze(axis))
    }
    fn slice(&mut self, x: &TchValue, axis: i64, start: i64, end: i64) -> TchValue {
        TchValue(x.0.narrow(axis, start, end - start))
    }
    fn to_f32(&mut self, x: &TchValue) -> TchValue {
        TchValue(x.0.to_kind(Kind::Float))
    }
}
