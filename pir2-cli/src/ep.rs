//! `--ep cpu|cuda|tensorrt`, `--ep-device N`, `--trt-cache DIR`: where ONNX Runtime runs the
//! GR00T graphs (`pir2 gr00t run|serve|bench`).

use std::path::PathBuf;

use anyhow::Result;

/// The execution provider a command asked for (resolved against the loaded ONNX Runtime
/// library when the graphs are loaded).
#[derive(Debug, Clone, PartialEq, Eq, clap::Args)]
pub struct EpOptions {
    /// ONNX Runtime execution provider for the GR00T graphs. `cuda` and `tensorrt` need the
    /// GPU build of ONNX Runtime (PyPI `onnxruntime-gpu`, same version) in ORT_DYLIB_PATH;
    /// a library without the provider is one error at start, never a CPU fallback.
    #[arg(long = "ep", id = "ep", value_name = "EP", value_parser = ["cpu", "cuda", "tensorrt"], default_value = "cpu")]
    pub name: String,
    /// CUDA device id for --ep cuda|tensorrt.
    #[arg(
        long = "ep-device",
        id = "ep_device",
        value_name = "EP_DEVICE",
        default_value_t = 0
    )]
    pub device: i32,
    /// --ep tensorrt: keep built engines and the timing cache here (the first start builds
    /// them, which takes minutes; later starts load them).
    #[arg(long)]
    pub trt_cache: Option<PathBuf>,
}

impl Default for EpOptions {
    fn default() -> Self {
        EpOptions {
            name: "cpu".into(),
            device: 0,
            trt_cache: None,
        }
    }
}

impl EpOptions {
    /// The ONNX Runtime options for these choices (single-threaded CPU sessions, or the GPU
    /// provider: a library without it fails when the graphs load, naming both).
    #[cfg(feature = "gr00t")]
    pub fn ort(&self) -> Result<pir2_backends::ort::OrtOptions> {
        use anyhow::Context;
        if self.trt_cache.is_some() && self.name != "tensorrt" {
            anyhow::bail!("--trt-cache is for --ep tensorrt (got --ep {})", self.name);
        }
        let provider =
            pir2_backends::ort::Provider::parse(&self.name, self.device, self.trt_cache.as_deref())
                .map_err(anyhow::Error::msg)
                .context("--ep")?;
        Ok(pir2_backends::ort::OrtOptions {
            provider,
            ..Default::default()
        })
    }

    /// Refuse GPU choices in a build that has no ONNX Runtime.
    #[cfg(not(feature = "gr00t"))]
    pub fn ort(&self) -> Result<()> {
        if self.name != "cpu" {
            anyhow::bail!("--ep {} needs a pir2 built with feature `gr00t`", self.name);
        }
        Ok(())
    }
}
