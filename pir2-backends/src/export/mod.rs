//! ONNX export without Python: a hand-written protobuf encoder ([`proto`]), a small graph
//! builder ([`graph`]) and the single-graph contract ([`contract`]) that the ONNX Runtime
//! backend loads.
//!
//! Graphs use the default domain at opset [`graph::OPSET`] (IR version [`graph::IR_VERSION`]);
//! weights are stored as initializers (raw little-endian `f32`). See [`contract`] for the
//! input/output names and shapes.

pub mod contract;
pub mod graph;
pub mod models;
pub mod ops;
pub mod proto;

use std::path::Path;

pub use contract::{ContractDims, SlowSpec};
pub use graph::GraphBuilder;
use proto::{DataType, Dim, ModelProto};

use crate::error::{Error, Result};

/// The named graph inputs created by [`contract_graph`].
#[derive(Debug, Clone)]
pub struct ContractValues {
    /// `x [B,H,A]`.
    pub x: String,
    /// `tau [B,H]`.
    pub tau: String,
    /// `obs_fast [B,n_obs,F]`.
    pub obs_fast: String,
    /// `obs_slow`, when the model has a slow input.
    pub obs_slow: Option<String>,
    /// `d_vis [B]` (int64), when declared.
    pub d_vis: Option<String>,
}

fn batch() -> Dim {
    Dim::Symbolic(contract::BATCH.to_string())
}

/// Start a graph that follows the [`contract`]: declares the inputs for `dims`.
pub fn contract_graph(name: &str, dims: &ContractDims) -> (GraphBuilder, ContractValues) {
    let mut g = GraphBuilder::new(name);
    let x = g.input(
        contract::X,
        DataType::Float,
        vec![
            batch(),
            Dim::Fixed(dims.horizon),
            Dim::Fixed(dims.action_dim),
        ],
    );
    let tau = g.input(
        contract::TAU,
        DataType::Float,
        vec![batch(), Dim::Fixed(dims.horizon)],
    );
    let obs_fast = g.input(
        contract::OBS_FAST,
        DataType::Float,
        vec![batch(), Dim::Fixed(dims.n_obs), Dim::Fixed(dims.fast_dim)],
    );
    let obs_slow = match dims.slow {
        SlowSpec::None => None,
        SlowSpec::Vector { dim } => Some(g.input(
            contract::OBS_SLOW,
            DataType::Float,
            vec![batch(), Dim::Fixed(dim)],
        )),
        SlowSpec::Tokens { tokens, dim } => Some(g.input(
            contract::OBS_SLOW,
            DataType::Float,
            vec![batch(), Dim::Fixed(tokens), Dim::Fixed(dim)],
        )),
    };
    let d_vis = dims
        .has_d_vis
        .then(|| g.input(contract::D_VIS, DataType::Int64, vec![batch()]));
    (
        g,
        ContractValues {
            x,
            tau,
            obs_fast,
            obs_slow,
            d_vis,
        },
    )
}

/// Declare `value` (`[B,H,A]`) as the contract output `v` and finish the model.
pub fn finish_contract(
    mut g: GraphBuilder,
    value: &str,
    dims: &ContractDims,
    model_kind: &str,
) -> ModelProto {
    g.output(
        value,
        contract::V,
        DataType::Float,
        vec![
            batch(),
            Dim::Fixed(dims.horizon),
            Dim::Fixed(dims.action_dim),
        ],
    );
    g.finish(vec![
        ("pir2.model".to_string(), model_kind.to_string()),
        (
            "pir2.contract".to_string(),
            "x,tau,obs_fast,obs_slow?,d_vis -> v".to_string(),
        ),
    ])
}

/// Write an encoded model to `path`.
pub fn write_model(model: &ModelProto, path: &Path) -> Result<()> {
    std::fs::write(path, model.encode()).map_err(|source| Error::OnnxWrite {
        path: path.to_path_buf(),
        source,
    })
}

/// A model the exporter knows how to write.
#[derive(Debug, Clone, PartialEq)]
pub enum ModelSpec {
    /// The flat MLP head.
    Mlp(models::MlpSpec),
    /// The conditional U-Net 1D with per-position FiLM.
    Unet(models::UnetSpec),
}

impl ModelSpec {
    /// The contract sizes.
    pub fn dims(&self) -> &ContractDims {
        match self {
            ModelSpec::Mlp(s) => &s.dims,
            ModelSpec::Unet(s) => &s.dims,
        }
    }
    /// `(name, shape)` of every weight the model reads.
    pub fn weight_shapes(&self) -> Vec<(String, Vec<usize>)> {
        match self {
            ModelSpec::Mlp(s) => s.weight_shapes(),
            ModelSpec::Unet(s) => s.weight_shapes(),
        }
    }
    /// A short name (`"mlp"`, `"unet"`).
    pub fn kind(&self) -> &'static str {
        match self {
            ModelSpec::Mlp(_) => "mlp",
            ModelSpec::Unet(_) => "unet",
        }
    }
    /// Run the definition on any [`ops::Ops`] sink.
    pub fn forward<O: ops::Ops, W: ops::WeightSource>(
        &self,
        o: &mut O,
        w: &W,
        inp: &models::Inputs<O::T>,
    ) -> Result<O::T> {
        match self {
            ModelSpec::Mlp(s) => s.forward(o, w, inp),
            ModelSpec::Unet(s) => s.forward(o, w, inp),
        }
    }
}

/// Build the ONNX model of `spec` with `weights` (weights become initializers).
pub fn export<W: ops::WeightSource>(spec: &ModelSpec, weights: &W) -> Result<ModelProto> {
    let dims = spec.dims();
    let (mut g, v) = contract_graph(spec.kind(), dims);
    let inp = models::Inputs {
        x: v.x,
        tau: v.tau,
        obs_fast: v.obs_fast,
        obs_slow: v.obs_slow,
        d_vis: v.d_vis,
    };
    let out = spec.forward(&mut g, weights, &inp)?;
    Ok(finish_contract(g, &out, dims, spec.kind()))
}

/// [`export`] and write the file.
pub fn export_to_file<W: ops::WeightSource>(
    spec: &ModelSpec,
    weights: &W,
    path: &Path,
) -> Result<()> {
    write_model(&export(spec, weights)?, path)
}
