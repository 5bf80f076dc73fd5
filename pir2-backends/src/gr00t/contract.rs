//! The export contract of every GR00T ONNX file, checked on load.
//!
//! Each file is described by a [`GraphSpec`]: its inputs and outputs with element types and
//! dimensions. A dimension is either the batch (`B`, fixed or dynamic), a named size that must
//! be fixed in the file and agree across all files of the checkpoint (`D_in`, `H`, …), or a
//! named size that may be dynamic (the token count `T`). [`Bindings`] carries the named sizes
//! from one file to the next, so a `D_in` of 1536 in the state encoder and 1024 in the action
//! encoder is reported with both files named. The tables are rendered in
//! `docs/gr00t-contract.md`.
//!
//! pir2 computes in `f32`. A spec with [`GraphSpec::half`] (the backbone's ViT and LLM:
//! GR00T's exporter writes `llm_bf16.onnx` by default) also takes a file whose float tensors
//! are `bfloat16` or `float16`: [`Graph::input`] converts each such input from `f32` and the
//! outputs are widened back to `f32`, per tensor, by the element type the file declares
//! ([`Declared::precision`]), never by its name.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use ::ort::session::{Session, SessionInputValue};
use ::ort::value::{TensorElementType, ValueType};

use crate::error::{Error, Result};
use crate::ort::{runtime, session_builder, OrtOptions};

/// Element type of a tensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Elem {
    /// `float32`.
    F32,
    /// `int64`.
    I64,
    /// `bool`.
    Bool,
}

/// How a float tensor of a file is stored. pir2 feeds and reads `f32`; the others are
/// converted at the graph's boundary (round to nearest even; a finite value the type cannot
/// hold is an error, see [`Graph::input`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Precision {
    /// `float32`.
    #[default]
    F32,
    /// `bfloat16` (GR00T's `use_bf16=True` exports).
    Bf16,
    /// `float16`.
    F16,
}

impl Precision {
    fn of(ty: TensorElementType) -> Option<Self> {
        match ty {
            TensorElementType::Float32 => Some(Precision::F32),
            TensorElementType::Bfloat16 => Some(Precision::Bf16),
            TensorElementType::Float16 => Some(Precision::F16),
            _ => None,
        }
    }
    /// The ONNX name, e.g. `bfloat16`.
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "float32",
            Precision::Bf16 => "bfloat16",
            Precision::F16 => "float16",
        }
    }
}

/// An ONNX element type in words (`float64`, `int32`, `bfloat16`…).
fn type_name(ty: TensorElementType) -> String {
    format!("{ty:?}").to_lowercase()
}

impl Elem {
    fn ort(self) -> TensorElementType {
        match self {
            Elem::F32 => TensorElementType::Float32,
            Elem::I64 => TensorElementType::Int64,
            Elem::Bool => TensorElementType::Bool,
        }
    }
    fn name(self) -> &'static str {
        match self {
            Elem::F32 => "float32",
            Elem::I64 => "int64",
            Elem::Bool => "bool",
        }
    }
}

/// One dimension of a tensor in the contract.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dim {
    /// The batch: fixed or dynamic, the same in every tensor of a file.
    Batch,
    /// Exactly this size.
    Fixed(usize),
    /// A named size, fixed in the file, the same wherever the name appears.
    Static(&'static str),
    /// A named size that may be dynamic; when fixed, it must agree with the other uses.
    Dynamic(&'static str),
}

impl std::fmt::Display for Dim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Dim::Batch => f.write_str("B"),
            Dim::Fixed(n) => write!(f, "{n}"),
            Dim::Static(n) => f.write_str(n),
            Dim::Dynamic(n) => write!(f, "{n}*"),
        }
    }
}

/// One input or output.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TensorSpec {
    /// Its name in the graph.
    pub name: &'static str,
    /// Element type.
    pub elem: Elem,
    /// Dimensions (the rank is their count).
    pub dims: &'static [Dim],
    /// Whether the tensor must be present (optional inputs are fed when declared).
    pub required: bool,
}

/// The contract of one file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GraphSpec {
    /// Role, for messages (e.g. "DiT").
    pub role: &'static str,
    /// Inputs; no others are allowed.
    pub inputs: &'static [TensorSpec],
    /// Outputs that must be present (others are ignored).
    pub outputs: &'static [TensorSpec],
    /// Whether its float tensors may be `bfloat16` or `float16` in the file (converted from
    /// and to `f32` at the boundary, see the module docs); otherwise they must be `float32`.
    pub half: bool,
}

const fn t(name: &'static str, elem: Elem, dims: &'static [Dim]) -> TensorSpec {
    TensorSpec {
        name,
        elem,
        dims,
        required: true,
    }
}
const fn opt(name: &'static str, elem: Elem, dims: &'static [Dim]) -> TensorSpec {
    TensorSpec {
        name,
        elem,
        dims,
        required: false,
    }
}

use Dim::{Batch, Dynamic, Fixed, Static};
use Elem::{Bool, F32, I64};

/// `state_encoder.onnx` (GR00T's exporter, unchanged): `S_in = n_obs · max_state_dim`.
pub const STATE_ENCODER: GraphSpec = GraphSpec {
    role: "state encoder",
    inputs: &[
        t("state", F32, &[Batch, Fixed(1), Static("S_in")]),
        t("embodiment_id", I64, &[Batch]),
    ],
    outputs: &[t("output", F32, &[Batch, Fixed(1), Static("D_in")])],
    half: false,
};

/// `action_encoder.onnx` with the πR² change: `timesteps` is per position `[B, H]`.
pub const ACTION_ENCODER: GraphSpec = GraphSpec {
    role: "action encoder",
    inputs: &[
        t("actions", F32, &[Batch, Static("H"), Static("A_max")]),
        t("timesteps", I64, &[Batch, Static("H")]),
        t("embodiment_id", I64, &[Batch]),
    ],
    outputs: &[t("output", F32, &[Batch, Static("H"), Static("D_in")])],
    half: false,
};

/// `dit.onnx` with the πR² change: `timestep` is per token `[B, 1+H]` (per-position AdaLN).
pub const DIT: GraphSpec = GraphSpec {
    role: "DiT",
    inputs: &[
        t("sa_embs", F32, &[Batch, Static("SA"), Static("D_in")]),
        t("vl_embs", F32, &[Batch, Dynamic("T"), Static("D_vl")]),
        t("timestep", I64, &[Batch, Static("SA")]),
        opt("image_mask", Bool, &[Batch, Dynamic("T")]),
        opt("backbone_attention_mask", Bool, &[Batch, Dynamic("T")]),
    ],
    outputs: &[t("output", F32, &[Batch, Static("SA"), Static("D_hid")])],
    half: false,
};

/// `action_decoder.onnx` (GR00T's exporter, unchanged).
pub const ACTION_DECODER: GraphSpec = GraphSpec {
    role: "action decoder",
    inputs: &[
        t("model_output", F32, &[Batch, Static("SA"), Static("D_hid")]),
        t("embodiment_id", I64, &[Batch]),
    ],
    outputs: &[t("output", F32, &[Batch, Static("SA"), Static("A_max")])],
    half: false,
};

/// `vl_self_attention.onnx` (GR00T's exporter, unchanged; optional).
pub const VL_SELF_ATTENTION: GraphSpec = GraphSpec {
    role: "VL self-attention",
    inputs: &[t(
        "hidden_states",
        F32,
        &[Batch, Dynamic("T"), Static("D_vl")],
    )],
    outputs: &[t("output", F32, &[Batch, Dynamic("T"), Static("D_vl")])],
    half: false,
};

/// `backbone.onnx`: ViT + LLM fused by the user (see `docs/gr00t-contract.md`).
pub const BACKBONE: GraphSpec = GraphSpec {
    role: "backbone",
    inputs: &[
        t(
            "pixel_values",
            F32,
            &[Dynamic("images"), Fixed(3), Static("crop"), Static("crop")],
        ),
        t("input_ids", I64, &[Batch, Dynamic("T")]),
        opt("attention_mask", I64, &[Batch, Dynamic("T")]),
    ],
    outputs: &[t("embeddings", F32, &[Batch, Dynamic("T"), Static("D_vl")])],
    half: false,
};

/// GR00T's ViT export (`export_onnx_n1d7.py`, `full_pipeline`: `vit_fp32.onnx`, or
/// `vit_bf16.onnx` with `use_bf16=True`): the patch rows of all images in, the merged image
/// tokens and the deepstack features out. Its grid is fixed at export, so every size is
/// fixed. Float tensors may be `bfloat16`/`float16` ([`GraphSpec::half`]).
pub const VIT: GraphSpec = GraphSpec {
    role: "ViT",
    inputs: &[t(
        "pixel_values",
        F32,
        &[Static("patches"), Static("patch_dim")],
    )],
    outputs: &[
        t(
            "image_embeds",
            F32,
            &[Static("image_tokens"), Static("D_vl")],
        ),
        t(
            "deepstack_features",
            F32,
            &[Static("deepstack"), Static("image_tokens"), Static("D_vl")],
        ),
    ],
    half: true,
};

/// Deepstack inputs the LLM export may declare, in layer order (GR00T's exporter writes at
/// most three).
pub const DEEPSTACK_INPUTS: [&str; 3] = ["deepstack_0", "deepstack_1", "deepstack_2"];

/// GR00T's LLM export (`llm_bf16.onnx`, the exporter's default, or `llm_fp32.onnx`): the
/// text model cut at `select_layer`, without the token embedding, returning the last kept
/// layer's hidden states (pre-norm). Float tensors (`inputs_embeds`, `deepstack_*`,
/// `embeddings`) may be `bfloat16`/`float16` ([`GraphSpec::half`]); the masks and positions
/// stay integer/bool.
pub const LLM: GraphSpec = GraphSpec {
    role: "LLM",
    inputs: &[
        t("inputs_embeds", F32, &[Batch, Dynamic("T"), Static("D_vl")]),
        t("attention_mask", I64, &[Batch, Dynamic("T")]),
        t("position_ids", I64, &[Fixed(3), Batch, Dynamic("T")]),
        opt("visual_pos_masks", Bool, &[Batch, Dynamic("T")]),
        opt(
            "deepstack_0",
            F32,
            &[Static("image_tokens"), Static("D_vl")],
        ),
        opt(
            "deepstack_1",
            F32,
            &[Static("image_tokens"), Static("D_vl")],
        ),
        opt(
            "deepstack_2",
            F32,
            &[Static("image_tokens"), Static("D_vl")],
        ),
    ],
    outputs: &[t("embeddings", F32, &[Batch, Dynamic("T"), Static("D_vl")])],
    half: true,
};

/// Named sizes collected across files, with the file each was first read from.
#[derive(Debug, Clone, Default)]
pub struct Bindings {
    dims: BTreeMap<&'static str, (usize, PathBuf)>,
}

impl Bindings {
    /// Pre-bind a size from the configuration (`source` names where it came from).
    pub fn bind(&mut self, name: &'static str, value: usize, source: impl Into<PathBuf>) {
        self.dims.insert(name, (value, source.into()));
    }
    /// A bound size.
    pub fn get(&self, name: &str) -> Option<usize> {
        self.dims.get(name).map(|(v, _)| *v)
    }
}

/// What a validated file declared.
#[derive(Debug, Clone, Default)]
pub struct Declared {
    /// Batch size if fixed in the file.
    pub batch: Option<usize>,
    /// Optional inputs that are present.
    pub optional_inputs: Vec<&'static str>,
    /// Storage of each float input and output of the spec that the file declares.
    pub floats: Vec<(&'static str, Precision)>,
}

impl Declared {
    /// Whether an optional input is declared.
    pub fn has(&self, name: &str) -> bool {
        self.optional_inputs.contains(&name)
    }
    /// How the float tensor `name` is stored in the file (`F32` for any other name).
    pub fn precision(&self, name: &str) -> Precision {
        self.floats
            .iter()
            .find(|(n, _)| *n == name)
            .map_or(Precision::F32, |(_, p)| *p)
    }
    /// The half-precision float tensors of the file, e.g. `inputs_embeds bfloat16`.
    pub fn half_tensors(&self) -> Vec<String> {
        self.floats
            .iter()
            .filter(|(_, p)| *p != Precision::F32)
            .map(|(n, p)| format!("{n} {}", p.name()))
            .collect()
    }
}

fn describe(ty: &ValueType) -> Option<(TensorElementType, Vec<i64>)> {
    match (ty.tensor_type(), ty.tensor_shape()) {
        (Some(t), Some(s)) => Some((t, s.iter().copied().collect())),
        _ => None,
    }
}

/// Check one file's declared inputs/outputs (`found`: name, element type, shape with `-1`
/// for dynamic) against `spec`, binding named sizes. Separated from ONNX Runtime so the
/// rules are unit-tested without the library.
pub fn check(
    spec: &GraphSpec,
    path: &Path,
    inputs: &[(String, TensorElementType, Vec<i64>)],
    outputs: &[(String, TensorElementType, Vec<i64>)],
    bindings: &mut Bindings,
) -> Result<Declared> {
    let bad = |tensor: &str, problem: String| Error::Gr00tContract {
        path: path.to_path_buf(),
        tensor: tensor.to_string(),
        problem,
    };
    let allowed: Vec<&str> = spec.inputs.iter().map(|t| t.name).collect();
    for (n, _, _) in inputs {
        if !allowed.contains(&n.as_str()) {
            return Err(bad(
                n,
                format!(
                    "unexpected input for the {} (allowed: {allowed:?})",
                    spec.role
                ),
            ));
        }
    }
    let mut declared = Declared::default();
    let mut batch: Option<i64> = None;
    let mut one = |ts: &TensorSpec,
                   found: Option<&(String, TensorElementType, Vec<i64>)>,
                   is_output: bool|
     -> Result<()> {
        let kind = if is_output { "output" } else { "input" };
        let Some((_, ty, shape)) = found else {
            if ts.required {
                let names: Vec<&str> = if is_output {
                    outputs.iter().map(|o| o.0.as_str()).collect()
                } else {
                    inputs.iter().map(|o| o.0.as_str()).collect()
                };
                return Err(bad(
                    ts.name,
                    format!(
                        "missing {kind} of the {} (the file declares {names:?})",
                        spec.role
                    ),
                ));
            }
            return Ok(());
        };
        if !ts.required {
            declared.optional_inputs.push(ts.name);
        }
        let want: Vec<String> = ts.dims.iter().map(|d| d.to_string()).collect();
        let float =
            Precision::of(*ty).filter(|p| ts.elem == F32 && (*p == Precision::F32 || spec.half));
        if *ty != ts.elem.ort() && float.is_none() {
            let expected = match ts.elem {
                F32 if spec.half => "float32, bfloat16 or float16 (converted from and to \
                                     float32 at the boundary)"
                    .to_string(),
                F32 => format!(
                    "float32 (the {} runs in float32; bfloat16/float16 files are taken only \
                     for the backbone's ViT and LLM)",
                    spec.role
                ),
                other => other.name().to_string(),
            };
            return Err(bad(
                ts.name,
                format!(
                    "{kind} of the {} has element type {}, expected {expected}",
                    spec.role,
                    type_name(*ty)
                ),
            ));
        }
        if let Some(p) = float {
            declared.floats.push((ts.name, p));
        }
        if shape.len() != ts.dims.len() {
            let hint = if ts.name.starts_with("timestep") && shape.len() + 1 == ts.dims.len() {
                "; this is GR00T's stock per-sample timestep: πR² needs one timestep per \
                 position (per-position AdaLN), see docs/gr00t-contract.md"
            } else {
                ""
            };
            return Err(bad(
                ts.name,
                format!(
                    "rank {} (shape {shape:?}), expected rank {} [{}]{hint}",
                    shape.len(),
                    ts.dims.len(),
                    want.join(", ")
                ),
            ));
        }
        for (k, (d, &n)) in ts.dims.iter().zip(shape).enumerate() {
            let fixed = (n > 0).then_some(n as usize);
            let mismatch = |exp: String| {
                bad(
                    ts.name,
                    format!(
                        "dimension {k} is {n} (shape {shape:?}), expected {exp} in [{}]",
                        want.join(", ")
                    ),
                )
            };
            match *d {
                Batch => {
                    if let Some(b) = fixed {
                        match batch {
                            Some(prev) if prev > 0 && prev as usize != b => {
                                return Err(mismatch(format!(
                                    "the batch {prev} of the other tensors"
                                )));
                            }
                            _ => batch = Some(b as i64),
                        }
                    }
                }
                Fixed(want) => {
                    // Outputs may have dims left unknown by shape inference.
                    if fixed != Some(want) && !(is_output && fixed.is_none()) {
                        return Err(mismatch(want.to_string()));
                    }
                }
                Static(name) | Dynamic(name) => {
                    let Some(v) = fixed else {
                        if matches!(d, Static(_)) && !is_output {
                            return Err(mismatch(format!(
                                "a fixed size `{name}` (only the batch{} may be dynamic)",
                                if spec
                                    .inputs
                                    .iter()
                                    .any(|t| t.dims.iter().any(|d| matches!(d, Dynamic(_))))
                                {
                                    " and the token count"
                                } else {
                                    ""
                                }
                            )));
                        }
                        continue;
                    };
                    match bindings.dims.get(name) {
                        Some((prev, src)) if *prev != v => {
                            return Err(mismatch(format!(
                                "`{name}` = {prev} (from `{}`)",
                                src.display()
                            )));
                        }
                        Some(_) => {}
                        None => {
                            bindings.dims.insert(name, (v, path.to_path_buf()));
                        }
                    }
                }
            }
        }
        Ok(())
    };
    for ts in spec.inputs {
        one(ts, inputs.iter().find(|(n, _, _)| n == ts.name), false)?;
    }
    for ts in spec.outputs {
        one(ts, outputs.iter().find(|(n, _, _)| n == ts.name), true)?;
    }
    declared.batch = batch.filter(|&b| b > 0).map(|b| b as usize);
    Ok(declared)
}

/// One loaded ONNX file with its contract checked.
pub struct Graph {
    session: Session,
    path: PathBuf,
    spec: GraphSpec,
    /// What the file declared.
    pub declared: Declared,
}

impl std::fmt::Debug for Graph {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Graph")
            .field("role", &self.spec.role)
            .field("path", &self.path)
            .field("declared", &self.declared)
            .finish()
    }
}

/// A feed: input name and value.
pub type Feed<'a> = (Cow<'a, str>, SessionInputValue<'a>);

impl Graph {
    /// Load `path` with ONNX Runtime (initialised once per process by [`crate::ort::runtime`])
    /// and check it against `spec`.
    pub fn load(
        path: &Path,
        spec: GraphSpec,
        opts: &OrtOptions,
        bindings: &mut Bindings,
    ) -> Result<Self> {
        let rt = runtime(opts.dylib_path.as_deref())?;
        let session_err = |e: String| Error::OrtSession {
            path: path.to_path_buf(),
            message: e,
        };
        if !path.exists() {
            return Err(Error::Read {
                path: path.to_path_buf(),
                source: std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    format!("the {} file is missing", spec.role),
                ),
            });
        }
        let session = session_builder(rt, opts, path)?
            .commit_from_file(path)
            .map_err(|e| {
                let message = e.to_string();
                match missing_kernel(&message) {
                    Some((op, node)) => Error::NoKernel {
                        path: path.to_path_buf(),
                        role: spec.role,
                        provider: opts.provider.ort_name(),
                        op: format!("{op} at {node}"),
                        hint: no_kernel_hint(&opts.provider),
                    },
                    None => session_err(message),
                }
            })?;
        let collect = |outlets: &[::ort::value::Outlet]| -> Result<Vec<_>> {
            outlets
                .iter()
                .map(|o| {
                    describe(o.dtype())
                        .map(|(t, s)| (o.name().to_string(), t, s))
                        .ok_or_else(|| Error::Gr00tContract {
                            path: path.to_path_buf(),
                            tensor: o.name().to_string(),
                            problem: format!("is not a tensor ({:?})", o.dtype()),
                        })
                })
                .collect()
        };
        let inputs = collect(session.inputs())?;
        let outputs = collect(session.outputs())?;
        let declared = check(&spec, path, &inputs, &outputs, bindings)?;
        Ok(Graph {
            session,
            path: path.to_path_buf(),
            spec,
            declared,
        })
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The feed of the float input `name` from `f32` data: borrowed when the file declares it
    /// `float32`, else converted into a new `bfloat16`/`float16` tensor (round to nearest
    /// even). A finite value the file's type cannot hold (beyond ±65504 for `float16`) is one
    /// error naming the file, the input and the value, never a silent infinity.
    pub fn input<'a>(
        &self,
        name: &'static str,
        shape: &[usize],
        data: &'a [f32],
    ) -> Result<Feed<'a>> {
        match self.declared.precision(name) {
            Precision::F32 => feed(name, shape, data),
            Precision::Bf16 => {
                self.converted(name, shape, data, half::bf16::from_f32, |h| h.to_f32())
            }
            Precision::F16 => {
                self.converted(name, shape, data, half::f16::from_f32, |h| h.to_f32())
            }
        }
    }

    fn converted<'a, T>(
        &self,
        name: &'static str,
        shape: &[usize],
        data: &[f32],
        narrow: fn(f32) -> T,
        widen: fn(T) -> f32,
    ) -> Result<Feed<'a>>
    where
        T: ::ort::value::PrimitiveTensorElementType + Copy + std::fmt::Debug + 'static,
    {
        let out = narrow_all(data, narrow, widen).map_err(|(i, x)| {
            let p = self.declared.precision(name);
            Error::input(
                format!("`{}` input `{name}` ({})", self.path.display(), p.name()),
                format!("values a {} can hold", p.name()),
                format!("{x} at element {i}"),
            )
        })?;
        let v = ::ort::value::Tensor::from_array((shape.to_vec(), out)).map_err(|e| {
            Error::input(
                format!("{name} {shape:?}"),
                "a tensor",
                format!("{} elements: {e}", data.len()),
            )
        })?;
        Ok((Cow::Borrowed(name), v.into()))
    }

    /// Run with `feeds` and copy each float output `(name, out)` into its `f32` buffer.
    pub fn run_many(
        &mut self,
        feeds: Vec<Feed<'_>>,
        outs: &mut [(&str, &mut Vec<f32>)],
    ) -> Result<()> {
        let path = self.path.clone();
        let run_err = |m: String| Error::Run {
            path: path.clone(),
            message: m,
        };
        let outputs = self
            .session
            .run(feeds)
            .map_err(|e| run_err(e.to_string()))?;
        for (name, out) in outs.iter_mut() {
            let v = outputs
                .get(*name)
                .ok_or_else(|| run_err(format!("no output `{name}`")))?;
            widen_into(v, out).map_err(|e| run_err(format!("output `{name}`: {e}")))?;
        }
        Ok(())
    }

    /// Run with `feeds` and copy the `f32` output `name` into `out`; returns its shape.
    pub fn run_into(
        &mut self,
        feeds: Vec<Feed<'_>>,
        name: &str,
        out: &mut Vec<f32>,
    ) -> Result<Vec<usize>> {
        let path = self.path.clone();
        let run_err = |m: String| Error::Run {
            path: path.clone(),
            message: m,
        };
        let outputs = self
            .session
            .run(feeds)
            .map_err(|e| run_err(e.to_string()))?;
        let v = outputs
            .get(name)
            .ok_or_else(|| run_err(format!("no output `{name}`")))?;
        let shape = widen_into(v, out).map_err(|e| run_err(format!("output `{name}`: {e}")))?;
        Ok(shape.iter().map(|&d| d.max(0) as usize).collect())
    }
}

/// `data` narrowed element-wise; `Err((index, value))` at the first finite value that
/// becomes infinite (out of the narrow type's range).
fn narrow_all<T: Copy>(
    data: &[f32],
    narrow: fn(f32) -> T,
    widen: fn(T) -> f32,
) -> std::result::Result<Vec<T>, (usize, f32)> {
    data.iter()
        .enumerate()
        .map(|(i, &x)| {
            let h = narrow(x);
            if x.is_finite() && !widen(h).is_finite() {
                Err((i, x))
            } else {
                Ok(h)
            }
        })
        .collect()
}

/// Copy a float output into `out` as `f32` (`bfloat16`/`float16` widened exactly); returns
/// its shape.
fn widen_into(
    v: &::ort::value::DynValue,
    out: &mut Vec<f32>,
) -> std::result::Result<Vec<i64>, String> {
    out.clear();
    let shape = match v.dtype().tensor_type() {
        Some(TensorElementType::Float32) => {
            let (shape, data) = v.try_extract_tensor::<f32>().map_err(|e| e.to_string())?;
            out.extend_from_slice(data);
            shape.to_vec()
        }
        Some(TensorElementType::Bfloat16) => {
            let (shape, data) = v
                .try_extract_tensor::<half::bf16>()
                .map_err(|e| e.to_string())?;
            out.extend(data.iter().map(|h| h.to_f32()));
            shape.to_vec()
        }
        Some(TensorElementType::Float16) => {
            let (shape, data) = v
                .try_extract_tensor::<half::f16>()
                .map_err(|e| e.to_string())?;
            out.extend(data.iter().map(|h| h.to_f32()));
            shape.to_vec()
        }
        other => return Err(format!("element type {other:?}, not a float tensor")),
    };
    Ok(shape)
}

/// `(op, "node `NAME`")` of ONNX Runtime's "Could not find an implementation for OP(VERSION) node
/// with name 'NODE'" (a provider without a kernel for an op at the graph's element types).
fn missing_kernel(message: &str) -> Option<(String, String)> {
    const KEY: &str = "Could not find an implementation for ";
    let rest = &message[message.find(KEY)? + KEY.len()..];
    let op = rest.split(" node").next()?.trim().to_string();
    let node = rest
        .split_once("with name '")
        .and_then(|(_, n)| n.split_once('\''))
        .map(|(n, _)| n)
        .filter(|n| !n.is_empty())
        .map_or_else(|| "an unnamed node".to_string(), |n| format!("node `{n}`"));
    Some((op, node))
}

/// What to do about a missing kernel on `provider` (see [`Error::NoKernel`]).
fn no_kernel_hint(provider: &crate::ort::Provider) -> String {
    let fix = "re-export the graph in float32 (GR00T's exporter: `use_bf16=False`, which \
               writes `llm_fp32.onnx` / `vit_fp32.onnx`)";
    match provider {
        crate::ort::Provider::Cpu => format!(
            "ONNX Runtime's CPU provider has no bfloat16 kernels for MatMul, Add, Mul, \
             Softmax and most other math ops (float16 it upcasts itself), so a bfloat16 \
             graph such as GR00T's default `llm_bf16.onnx` does not run on it: run with \
             `--ep cuda` or `--ep tensorrt` (the GPU build of ONNX Runtime), or {fix}"
        ),
        _ => format!("run with another provider, or {fix}"),
    }
}

/// Build a feed from a flat slice and a shape.
pub fn feed<'a, T>(name: &'static str, shape: &[usize], data: &'a [T]) -> Result<Feed<'a>>
where
    T: ::ort::value::PrimitiveTensorElementType + Clone + std::fmt::Debug + 'static,
{
    let v = ::ort::value::TensorRef::from_array_view((shape.to_vec(), data)).map_err(|e| {
        Error::input(
            format!("{name} {shape:?}"),
            "a tensor",
            format!("{} elements: {e}", data.len()),
        )
    })?;
    Ok((Cow::Borrowed(name), v.into()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn f(name: &str, ty: TensorElementType, s: &[i64]) -> (String, TensorElementType, Vec<i64>) {
        (name.to_string(), ty, s.to_vec())
    }
    const F: TensorElementType = TensorElementType::Float32;
    const I: TensorElementType = TensorElementType::Int64;

    #[test]
    fn binds_named_dims_across_files_and_names_both_files() {
        let mut b = Bindings::default();
        let p1 = Path::new("a/state_encoder.onnx");
        check(
            &STATE_ENCODER,
            p1,
            &[f("state", F, &[1, 1, 64]), f("embodiment_id", I, &[1])],
            &[f("output", F, &[1, 1, 32])],
            &mut b,
        )
        .unwrap();
        assert_eq!(b.get("D_in"), Some(32));
        let p2 = Path::new("a/action_encoder.onnx");
        let e = check(
            &ACTION_ENCODER,
            p2,
            &[
                f("actions", F, &[1, 4, 8]),
                f("timesteps", I, &[1, 4]),
                f("embodiment_id", I, &[1]),
            ],
            &[f("output", F, &[1, 4, 16])],
            &mut b,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("action_encoder.onnx")
                && e.contains("`output`")
                && e.contains("state_encoder.onnx")
                && e.contains("D_in"),
            "{e}"
        );
    }

    #[test]
    fn half_float_tensors_are_taken_where_the_spec_allows_them() {
        const BF: TensorElementType = TensorElementType::Bfloat16;
        const H: TensorElementType = TensorElementType::Float16;
        const BOOL: TensorElementType = TensorElementType::Bool;
        let llm = |emb: TensorElementType, out: TensorElementType| {
            let mut b = Bindings::default();
            check(
                &LLM,
                Path::new("llm_bf16.onnx"),
                &[
                    f("inputs_embeds", emb, &[1, -1, 16]),
                    f("attention_mask", I, &[1, -1]),
                    f("position_ids", I, &[3, 1, -1]),
                    f("visual_pos_masks", BOOL, &[1, -1]),
                    f("deepstack_0", H, &[4, 16]),
                ],
                &[f("embeddings", out, &[1, -1, 16])],
                &mut b,
            )
        };
        let d = llm(BF, BF).unwrap();
        assert_eq!(d.precision("inputs_embeds"), Precision::Bf16);
        assert_eq!(d.precision("deepstack_0"), Precision::F16);
        assert_eq!(d.precision("embeddings"), Precision::Bf16);
        assert_eq!(d.precision("attention_mask"), Precision::F32);
        assert_eq!(
            d.half_tensors(),
            [
                "inputs_embeds bfloat16",
                "deepstack_0 float16",
                "embeddings bfloat16"
            ]
        );
        assert_eq!(llm(F, F).unwrap().half_tensors(), ["deepstack_0 float16"]);
        // Neither float32 nor half: one error naming the tensor and the type.
        for (ty, name) in [
            (TensorElementType::Float64, "float64"),
            (TensorElementType::Int32, "int32"),
        ] {
            let e = llm(ty, F).unwrap_err().to_string();
            assert!(
                e.contains("llm_bf16.onnx")
                    && e.contains("`inputs_embeds`")
                    && e.contains(name)
                    && e.contains("expected float32, bfloat16 or float16"),
                "{e}"
            );
        }
        let e = llm(F, TensorElementType::Float64).unwrap_err().to_string();
        assert!(e.contains("`embeddings`") && e.contains("output"), "{e}");
        // The integer inputs stay integer.
        let mut b = Bindings::default();
        let e = check(
            &LLM,
            Path::new("llm.onnx"),
            &[
                f("inputs_embeds", F, &[1, -1, 16]),
                f("attention_mask", BF, &[1, -1]),
                f("position_ids", I, &[3, 1, -1]),
            ],
            &[f("embeddings", F, &[1, -1, 16])],
            &mut b,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("`attention_mask`") && e.contains("expected int64"),
            "{e}"
        );
        // A graph of the action head stays float32.
        let mut b = Bindings::default();
        let e = check(
            &STATE_ENCODER,
            Path::new("state_encoder.onnx"),
            &[f("state", BF, &[1, 1, 8]), f("embodiment_id", I, &[1])],
            &[f("output", F, &[1, 1, 32])],
            &mut b,
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("`state`")
                && e.contains("bfloat16")
                && e.contains("state encoder runs in float32"),
            "{e}"
        );
    }

    #[test]
    fn narrowing_rounds_to_nearest_even_and_refuses_overflow() {
        let bf = |x: f32| half::bf16::from_f32(x);
        let to = |h: half::bf16| h.to_f32();
        // 1 + 2⁻⁸ is halfway between two bfloat16 values: ties to even (1.0); just above
        // rounds up to 1 + 2⁻⁷.
        let got = narrow_all(&[1.0 + 1.0 / 256.0, 1.0 + 1.5 / 256.0, -3.0], bf, to).unwrap();
        let got: Vec<f32> = got.into_iter().map(to).collect();
        assert_eq!(got, [1.0, 1.0 + 1.0 / 128.0, -3.0]);
        // float16 stops at 65504: a finite value beyond is refused by index and value,
        // an infinity or NaN the caller fed passes through.
        let h = |x: f32| half::f16::from_f32(x);
        let hto = |x: half::f16| x.to_f32();
        assert_eq!(
            narrow_all(&[1.0, 70000.0], h, hto).unwrap_err(),
            (1, 70000.0)
        );
        assert!(narrow_all(&[65504.0, f32::INFINITY], h, hto).is_ok());
        assert!(narrow_all(&[3.0e38], bf, to).is_ok());
    }

    #[test]
    fn missing_kernel_messages_are_parsed() {
        let m = "[ONNXRuntimeError] : 9 : NOT_IMPLEMENTED : Could not find an implementation \
                 for MatMul(13) node with name '/layers.0/self_attn/q_proj/MatMul'";
        assert_eq!(
            missing_kernel(m),
            Some((
                "MatMul(13)".to_string(),
                "node `/layers.0/self_attn/q_proj/MatMul`".to_string()
            ))
        );
        let m = "Could not find an implementation for Add(14) node with name ''";
        assert_eq!(
            missing_kernel(m),
            Some(("Add(14)".to_string(), "an unnamed node".to_string()))
        );
        assert_eq!(
            missing_kernel("Load model from x failed: no such file"),
            None
        );
    }

    #[test]
    fn per_sample_timesteps_are_rejected_with_the_rank() {
        let mut b = Bindings::default();
        let e = check(
            &ACTION_ENCODER,
            Path::new("x.onnx"),
            &[
                f("actions", F, &[1, 4, 8]),
                f("timesteps", I, &[1]),
                f("embodiment_id", I, &[1]),
            ],
            &[f("output", F, &[1, 4, 16])],
            &mut b,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("`timesteps`") && e.contains("rank 1"), "{e}");
    }

    #[test]
    fn dynamic_static_dims_and_unknown_inputs_are_rejected() {
        let mut b = Bindings::default();
        let e = check(
            &STATE_ENCODER,
            Path::new("s.onnx"),
            &[f("state", F, &[-1, 1, -1]), f("embodiment_id", I, &[-1])],
            &[f("output", F, &[-1, 1, 32])],
            &mut b,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("`state`") && e.contains("S_in"), "{e}");
        let e = check(
            &STATE_ENCODER,
            Path::new("s.onnx"),
            &[
                f("state", F, &[1, 1, 8]),
                f("embodiment_id", I, &[1]),
                f("extra", F, &[1]),
            ],
            &[f("output", F, &[1, 1, 32])],
            &mut b,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("`extra`") && e.contains("unexpected"), "{e}");
    }
}
