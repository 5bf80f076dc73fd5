//! Where ONNX Runtime runs a graph: the CPU, or an NVIDIA GPU through CUDA or TensorRT.
//!
//! The execution provider is a property of the *library* as much as of the session: the CPU
//! build of ONNX Runtime (PyPI `onnxruntime`, what `scripts/setup-native.sh` installs) has only
//! the CPU provider; the GPU build (PyPI `onnxruntime-gpu`, same version, with CUDA and cuDNN
//! on the loader's path, TensorRT for the TensorRT provider) adds `CUDAExecutionProvider` and
//! `TensorrtExecutionProvider`. Point `ORT_DYLIB_PATH` at the GPU build's `libonnxruntime.so`
//! to use them.
//!
//! A provider that was asked for is never silently replaced by the CPU: if the loaded library
//! lacks it, or it fails to register (no device, missing CUDA libraries), session creation
//! fails with [`Error::OrtProvider`](crate::Error::OrtProvider) naming the library, the provider and what the library
//! offers. With TensorRT, nodes TensorRT cannot take run on CUDA (ONNX Runtime partitions
//! the graph), not on the CPU.

use std::path::{Path, PathBuf};

use ::ort::ep;
use ::ort::session::builder::SessionBuilder;

use super::OrtRuntime;
use crate::error::{Error, Result};

/// The execution provider of a session (see the module docs).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub enum Provider {
    /// ONNX Runtime's CPU provider (every build has it).
    #[default]
    Cpu,
    /// CUDA on GPU `device`.
    Cuda {
        /// CUDA device id.
        device: i32,
    },
    /// TensorRT on GPU `device`, CUDA for what TensorRT does not take.
    TensorRt {
        /// CUDA device id.
        device: i32,
        /// Where TensorRT keeps its built engines and timing cache between runs (building
        /// an engine takes minutes; without a cache every start builds again).
        cache_dir: Option<PathBuf>,
    },
}

/// Whether the loaded library has a provider.
type Probe = fn() -> bool;

/// Providers this module can name in an error (what the loaded library offers).
const KNOWN: [(&str, Probe); 3] = [
    ("CPUExecutionProvider", available::<ep::CPU>),
    ("CUDAExecutionProvider", available::<ep::CUDA>),
    ("TensorrtExecutionProvider", available::<ep::TensorRT>),
];

fn available<E: ::ort::ep::ExecutionProvider>() -> bool {
    E::is_available().unwrap_or(false)
}

impl Provider {
    /// Parse a command-line choice: `cpu`, `cuda` or `tensorrt` (device id and TensorRT
    /// cache directory given separately). An unknown name is an error naming the choices.
    pub fn parse(name: &str, device: i32, cache_dir: Option<&Path>) -> Result<Self, String> {
        match name {
            "cpu" => Ok(Provider::Cpu),
            "cuda" => Ok(Provider::Cuda { device }),
            "tensorrt" | "trt" => Ok(Provider::TensorRt {
                device,
                cache_dir: cache_dir.map(Path::to_path_buf),
            }),
            other => Err(format!(
                "unknown execution provider `{other}` (one of: cpu, cuda, tensorrt)"
            )),
        }
    }

    /// ONNX Runtime's name of the provider, e.g. `CUDAExecutionProvider`.
    pub fn ort_name(&self) -> &'static str {
        match self {
            Provider::Cpu => "CPUExecutionProvider",
            Provider::Cuda { .. } => "CUDAExecutionProvider",
            Provider::TensorRt { .. } => "TensorrtExecutionProvider",
        }
    }

    /// A short description for run summaries, e.g. `CUDA (device 0)`.
    pub fn describe(&self) -> String {
        match self {
            Provider::Cpu => "CPU".into(),
            Provider::Cuda { device } => format!("CUDA (device {device})"),
            Provider::TensorRt { device, cache_dir } => match cache_dir {
                Some(d) => format!("TensorRT (device {device}, engine cache {})", d.display()),
                None => format!("TensorRT (device {device}, no engine cache)"),
            },
        }
    }

    /// Whether the loaded library `rt` has this provider.
    pub fn is_available(&self, rt: &OrtRuntime) -> bool {
        let _ = rt; // the library is process-wide; `rt` proves it is loaded
        match self {
            Provider::Cpu => true,
            Provider::Cuda { .. } => available::<ep::CUDA>(),
            Provider::TensorRt { .. } => available::<ep::TensorRT>(),
        }
    }

    /// Register the provider on `builder` (nothing for the CPU). Fails with
    /// [`Error::OrtProvider`](crate::Error::OrtProvider) when the library lacks it or it cannot start.
    pub(crate) fn register(
        &self,
        rt: &OrtRuntime,
        builder: SessionBuilder,
    ) -> Result<SessionBuilder> {
        if *self == Provider::Cpu {
            return Ok(builder);
        }
        let err = |reason: String| Error::OrtProvider {
            provider: self.ort_name(),
            path: rt.path().to_path_buf(),
            version: rt.version().to_string(),
            reason,
        };
        if !self.is_available(rt) {
            let offers: Vec<&str> = KNOWN
                .iter()
                .filter(|(_, has)| has())
                .map(|(name, _)| *name)
                .collect();
            return Err(err(format!(
                "the library does not have it (it offers: {}); install the GPU build of the \
                 same version (PyPI `onnxruntime-gpu`) and point ORT_DYLIB_PATH at its \
                 libonnxruntime",
                offers.join(", ")
            )));
        }
        let eps = match self {
            Provider::Cpu => Vec::new(),
            Provider::Cuda { device } => vec![ep::CUDA::default()
                .with_device_id(*device)
                .build()
                .error_on_failure()],
            Provider::TensorRt { device, cache_dir } => {
                let mut trt = ep::TensorRT::default().with_device_id(*device);
                if let Some(dir) = cache_dir {
                    std::fs::create_dir_all(dir).map_err(|e| {
                        err(format!(
                            "cannot create the engine cache {}: {e}",
                            dir.display()
                        ))
                    })?;
                    let dir = dir.display().to_string();
                    trt = trt
                        .with_engine_cache(true)
                        .with_engine_cache_path(&dir)
                        .with_timing_cache(true)
                        .with_timing_cache_path(&dir);
                }
                vec![
                    trt.build().error_on_failure(),
                    ep::CUDA::default()
                        .with_device_id(*device)
                        .build()
                        .error_on_failure(),
                ]
            }
        };
        builder
            .with_execution_providers(eps)
            .map_err(|e| err(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn choices_parse_and_describe() {
        assert_eq!(Provider::parse("cpu", 0, None), Ok(Provider::Cpu));
        assert_eq!(
            Provider::parse("cuda", 1, None),
            Ok(Provider::Cuda { device: 1 })
        );
        let trt = Provider::parse("tensorrt", 0, Some(Path::new("cache"))).unwrap();
        assert_eq!(trt.ort_name(), "TensorrtExecutionProvider");
        assert!(trt.describe().contains("engine cache cache"));
        let e = Provider::parse("rocm", 0, None).unwrap_err();
        assert!(e.contains("rocm") && e.contains("cuda"), "{e}");
    }
}
