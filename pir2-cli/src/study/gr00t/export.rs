//! `pir2 gr00t export`: a fine-tuned GR00T N1.7 step directory to the checkpoint layout of
//! `docs/gr00t-contract.md` (feature `gr00t`).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use candle_core::Device;
use pir2_backends::gr00t::n17::Gr00tN17Head;
use pir2_backends::gr00t::{EmbodimentConfig, Normalizer};

use super::train::check_head_fits;

/// What `pir2 gr00t export` wrote.
#[derive(Debug, Clone)]
pub struct Gr00tExportSummary {
    /// The output directory.
    pub out: PathBuf,
    /// The files written, relative to `out`.
    pub files: Vec<String>,
    /// The chunk length the graphs take.
    pub horizon: usize,
    /// Rows of the delay table minus one.
    pub d_vis_max: usize,
    /// What the head was trained as (`[policy] trained`).
    pub trained: String,
}

/// The first of `dirs` holding `name`, or one error naming every place looked at.
fn find_in(dirs: &[&Path], name: &str, what: &str) -> Result<PathBuf> {
    for d in dirs {
        let p = d.join(name);
        if p.is_file() {
            return Ok(p);
        }
    }
    let places: Vec<String> = dirs
        .iter()
        .map(|d| d.join(name).display().to_string())
        .collect();
    bail!("no {what}: looked for {}", places.join(" and "))
}

/// `pir2 gr00t export STEP_DIR --out OUT`: a fine-tuned N1.7 step directory of `pir2 gr00t train`
/// (`model.safetensors` + `config.json`; `statistics.json` and `embodiment.toml` in it or in
/// the run root above it) → the checkpoint layout of `docs/gr00t-contract.md` in `out`:
/// `onnx/{state_encoder,action_encoder,dit,action_decoder}.onnx` (+ `vl_self_attention.onnx`
/// when the head has one), `pir2_gr00t.safetensors`, `statistics.json`, `embodiment.toml`
/// (with its `[policy]` table written out). `out` must not exist or be empty; the files
/// are written to a sibling directory first and moved into place at the end, so a failed
/// export leaves nothing behind. The backbone (`onnx/backbone.onnx`) and the tokenizer are
/// not part of the head and are not written.
pub fn export(step: &Path, out: &Path) -> Result<Gr00tExportSummary> {
    use pir2_backends::gr00t::n17::export::{export_gr00t_n17, WeightStorage};

    if out.exists() {
        let empty = out.is_dir()
            && std::fs::read_dir(out)
                .with_context(|| format!("reading {}", out.display()))?
                .next()
                .is_none();
        if !empty {
            bail!(
                "{} already exists and is not empty; choose a new --out directory (nothing \
                 was written)",
                out.display()
            );
        }
    }
    if !step.is_dir() {
        bail!(
            "{} is not a directory (a `pir2 gr00t train` step directory)",
            step.display()
        );
    }
    let root = step.parent().unwrap_or(step);
    let emb_path = find_in(&[step, root], "embodiment.toml", "embodiment")?;
    let stats_path = find_in(&[step, root], "statistics.json", "statistics")?;
    let emb = EmbodimentConfig::load(&emb_path)
        .with_context(|| format!("embodiment {}", emb_path.display()))?;
    // The statistics must serve the embodiment (every group, every statistic its norm needs).
    Normalizer::load(&stats_path, &emb)
        .with_context(|| format!("statistics {}", stats_path.display()))?;
    let head = Gr00tN17Head::load(step, &Device::Cpu)
        .with_context(|| format!("GR00T N1.7 step checkpoint {}", step.display()))?;
    let c = head.config().clone();
    check_head_fits(&emb, &c, step, &emb_path)?;
    let delay = format!(
        "{}{}",
        pir2_backends::gr00t::n17::PREFIX,
        pir2_backends::gr00t::n17::DELAY_EMBEDDING
    );
    let Some(table) = head.delay_embedding() else {
        bail!(
            "{}: no delay table `{delay}` in {}; export a πR²-fine-tuned head (a `pir2 train \
             gr00t` step directory), not a base GR00T checkpoint",
            step.display(),
            pir2_backends::gr00t::n17::SINGLE_FILE
        );
    };
    if table.dims() != [emb.d_vis_max + 1, c.input_embedding_dim] {
        bail!(
            "{}: the delay table `{delay}` has shape {:?}, the embodiment {} needs \
             [d_vis_max + 1, D_in] = [{}, {}]",
            step.display(),
            table.dims(),
            emb_path.display(),
            emb.d_vis_max + 1,
            c.input_embedding_dim
        );
    }
    let exported = export_gr00t_n17(&head, emb.horizon)
        .with_context(|| format!("exporting {}", step.display()))?;
    // The export holds its own copy of the weights; at full size the head is gigabytes.
    drop(head);

    // Write next to `out`, then move into place.
    let name = out
        .file_name()
        .with_context(|| format!("{} has no directory name", out.display()))?;
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).with_context(|| format!("creating {}", parent.display()))?;
    let tmp = parent.join(format!(
        ".{}.partial-{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).with_context(|| format!("removing {}", tmp.display()))?;
    }
    std::fs::create_dir_all(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
    let d_vis_max = exported.d_vis_max;
    let written = (|| -> Result<Vec<String>> {
        let mut files = exported.write(&tmp, WeightStorage::Auto)?;
        std::fs::copy(&stats_path, tmp.join("statistics.json"))
            .with_context(|| format!("copying {}", stats_path.display()))?;
        std::fs::write(tmp.join("embodiment.toml"), emb.to_toml()?)
            .with_context(|| format!("writing {}", tmp.join("embodiment.toml").display()))?;
        files.extend(["statistics.json".into(), "embodiment.toml".into()]);
        Ok(files)
    })();
    let files = match written {
        Ok(f) => f,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
    };
    if out.exists() {
        // Checked empty above.
        std::fs::remove_dir(out).with_context(|| format!("replacing {}", out.display()))?;
    }
    std::fs::rename(&tmp, out)
        .with_context(|| format!("moving {} to {}", tmp.display(), out.display()))?;
    Ok(Gr00tExportSummary {
        out: out.to_path_buf(),
        files,
        horizon: emb.horizon,
        d_vis_max,
        trained: pir2_backends::gr00t::policy_name(emb.policy.trained).to_string(),
    })
}
