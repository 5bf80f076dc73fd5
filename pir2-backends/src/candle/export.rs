//! From the candle models to the exporter: [`spec_from_config`] turns a candle [`Config`] +
//! [`Stats`] into the [`ModelSpec`] the exporter and the libtorch tracer run, and
//! [`CandleModel`] / [`Checkpoint`] are [`WeightSource`]s (same names, same layouts).

use super::CandleModel;
use crate::checkpoint::Checkpoint;
use crate::config::{self, Config, FilmMode, ModelConfig, Stats};
use crate::error::{Error, Result};
use crate::export::contract::ContractDims;
use crate::export::models::{Film, MlpSpec, ObsNorm, UnetSpec};
use crate::export::ops::WeightSource;
use crate::export::{export_to_file, ModelSpec};

fn dims(spec: &config::Spec) -> ContractDims {
    ContractDims {
        horizon: spec.horizon,
        action_dim: spec.action_dim,
        n_obs: spec.n_obs,
        fast_dim: spec.fast_dim,
        slow: spec.slow,
        has_d_vis: true,
    }
}

fn norm(stats: &Stats) -> ObsNorm {
    ObsNorm {
        fast: (stats.fast.mean.clone(), stats.fast.std.clone()),
        fast_diff: (stats.fast_diff.mean.clone(), stats.fast_diff.std.clone()),
        slow: (stats.slow.mean.clone(), stats.slow.std.clone()),
    }
}

/// The exportable definition of a candle model configuration (MLP and U-Net; the DiT is
/// not exportable yet).
pub fn spec_from_config(cfg: &Config, stats: &Stats) -> Result<ModelSpec> {
    let d = dims(&cfg.spec);
    let norm = norm(stats);
    let d_vis_max = cfg.spec.d_vis_max;
    match &cfg.model {
        ModelConfig::Mlp(m) => Ok(ModelSpec::Mlp(MlpSpec {
            dims: d,
            width: m.width,
            depth: m.depth,
            tau_freqs: m.tau_freqs,
            dvis_dim: m.dvis_dim,
            d_vis_max,
            norm,
        })),
        ModelConfig::UNet(u) => Ok(ModelSpec::Unet(UnetSpec {
            dims: d,
            widths: u.widths.clone(),
            kernel: u.kernel,
            groups: u.groups,
            tau_dim: u.tau_dim,
            dvis_dim: u.dvis_dim,
            d_vis_max,
            film: match u.film {
                FilmMode::Shared => Film::Shared,
                FilmMode::PerPositionHeads => Film::PerPositionHeads,
                FilmMode::PerPositionTau => Film::PerPositionTau,
            },
            norm,
        })),
        ModelConfig::Dit(_) => Err(Error::Unsupported {
            model: "DiT",
            message: "ONNX export of the DiT head is not implemented".to_string(),
        }),
    }
}

impl WeightSource for CandleModel {
    fn weight(&self, model: &'static str, name: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let (_, var) =
            self.vars()
                .iter()
                .find(|(n, _)| n == name)
                .ok_or_else(|| Error::MissingWeight {
                    model,
                    name: name.to_string(),
                })?;
        if var.dims() != shape {
            return Err(Error::WeightShape {
                model,
                name: name.to_string(),
                expected: shape.to_vec(),
                got: var.dims().to_vec(),
            });
        }
        var.as_tensor()
            .flatten_all()
            .and_then(|t| t.to_vec1::<f32>())
            .map_err(|e| Error::Unsupported {
                model,
                message: format!("cannot read weight `{name}`: {e}"),
            })
    }
}

impl WeightSource for Checkpoint {
    fn weight(&self, model: &'static str, name: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let t = self.tensors.get(name).ok_or_else(|| Error::MissingWeight {
            model,
            name: name.to_string(),
        })?;
        if t.shape != shape {
            return Err(Error::WeightShape {
                model,
                name: name.to_string(),
                expected: shape.to_vec(),
                got: t.shape.clone(),
            });
        }
        Ok(t.data.clone())
    }
}

/// Export a candle model to an ONNX file (the graph takes and returns normalised actions,
/// exactly like the candle model; observations are normalised inside the graph).
pub fn export_candle_model(model: &CandleModel, path: &std::path::Path) -> Result<()> {
    let spec = spec_from_config(model.config(), model.stats())?;
    export_to_file(&spec, model, path)
}

/// Export a checkpoint directory (`config.json`, `stats.json`, `model.safetensors`) to ONNX.
pub fn export_checkpoint(ck: &Checkpoint, path: &std::path::Path) -> Result<()> {
    let spec = spec_from_config(&ck.config, &ck.stats)?;
    export_to_file(&spec, ck, path)
}
