//! Choosing the candle device by name: `cpu`, `cuda[:N]`, `metal[:N]`.

use candle_core::Device;

use crate::error::{Error, Result};

/// The candle device named `spec`: `cpu`, `cuda` / `cuda:N` (NVIDIA GPU `N`, default 0) or
/// `metal` / `metal:N` (Apple GPU `N`).
///
/// A GPU needs pir2 built with its feature (`--features cuda` or `--features metal`, which
/// turn on candle's backend of the same name). Without it, naming one is
/// [`Error::Config`] saying which feature to build with: candle's own constructors exist
/// in every build and would only say "not compiled with cuda support". With the feature, a
/// device that cannot be opened (no driver, no GPU `N`) is [`Error::Config`] carrying
/// candle's message. Anything else is [`Error::Config`] listing the accepted names.
///
/// ```
/// use pir2_backends::candle::device;
/// assert!(device("cpu").unwrap().is_cpu());
/// assert!(device("tpu").is_err());
/// ```
pub fn device(spec: &str) -> Result<Device> {
    let bad = || {
        Error::config(
            "device",
            format!("`{spec}` is not a device; use cpu, cuda, cuda:N, metal or metal:N"),
        )
    };
    let (kind, ordinal) = match spec.split_once(':') {
        Some((k, n)) => (k, n.parse::<usize>().map_err(|_| bad())?),
        None => (spec, 0),
    };
    match kind {
        "cpu" if !spec.contains(':') => Ok(Device::Cpu),
        "cuda" => gpu(spec, "cuda", cfg!(feature = "cuda"), || {
            Device::new_cuda(ordinal)
        }),
        "metal" => gpu(spec, "metal", cfg!(feature = "metal"), || {
            Device::new_metal(ordinal)
        }),
        _ => Err(bad()),
    }
}

/// Open a GPU of the backend `feature` if this build has it.
fn gpu(
    spec: &str,
    feature: &str,
    built: bool,
    open: impl FnOnce() -> candle_core::Result<Device>,
) -> Result<Device> {
    if !built {
        return Err(Error::config(
            "device",
            format!(
                "`{spec}` needs pir2 built with `--features {feature}` (candle's {feature} \
                 backend); this build runs on the cpu only"
            ),
        ));
    }
    open().map_err(|e| Error::config("device", format!("`{spec}`: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_parsed_and_a_missing_backend_names_its_feature() {
        assert!(device("cpu").unwrap().is_cpu());
        for bad in ["", "gpu", "cpu:0", "cuda:", "cuda:x", "metal:-1", "CUDA"] {
            let e = device(bad).unwrap_err().to_string();
            assert!(e.contains("cuda:N"), "{bad}: {e}");
        }
        if !cfg!(feature = "cuda") {
            for spec in ["cuda", "cuda:1"] {
                let e = device(spec).unwrap_err().to_string();
                assert!(e.contains("--features cuda") && e.contains(spec), "{e}");
            }
        }
        if !cfg!(feature = "metal") {
            let e = device("metal:0").unwrap_err().to_string();
            assert!(e.contains("--features metal"), "{e}");
        }
    }
}
