//! `pir2 gr00t <verb>`: the GR00T N1.7 commands (feature `gr00t`; a build without it offers
//! the same verbs and options, and each says how to build it). The work is
//! [`crate::study::gr00t`]'s and `crate::bench::gr00t`'s; this module prints what a user
//! reads.

use std::path::PathBuf;

use anyhow::Result;

use crate::ep::EpOptions;
use crate::study::gr00t::{Gr00tFeaturesOptions, Gr00tTrainOptions};

/// The verbs of `pir2 gr00t`.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum Gr00tCmd {
    /// Precompute GR00T N1.7's frozen backbone features (the checkpoint's ONNX backbone and
    /// tokenizer, run as `pir2 run` runs them) on every frame of a LeRobotDataset v3.0,
    /// written as the `--features` file of `pir2 gr00t train` (needs the `ffmpeg` program for
    /// video cameras).
    Features(Gr00tFeaturesOptions),
    /// πR² fine-tuning of a GR00T N1.7 checkpoint's action head on a dataset and its
    /// precomputed backbone features, with candle.
    Train(Box<Gr00tTrainOptions>),
    /// A `pir2 gr00t train` step directory to the GR00T checkpoint layout
    /// (docs/gr00t-contract.md), which `pir2 run` runs.
    Export(Gr00tExportOptions),
    /// One-NFE latency of a GR00T export's action head and backbone, and the delay `d` it
    /// implies.
    Bench(Gr00tBenchOptions),
    /// Write a small example checkpoint with random weights (the xArm6 + XHand embodiment,
    /// N1.7's shapes at tiny widths: action head, stand-in backbone, tokenizer) that
    /// `pir2 run gr00t-xarm-xhand --emulate` runs; no download, no Python.
    Example(Gr00tExampleOptions),
    /// A GR00T N1.7 checkpoint as Isaac-GR00T writes it (config.json, safetensors,
    /// processor_config.json, statistics.json, embodiment_id.json) to the checkpoint layout
    /// `pir2 run` and `pir2 gr00t train` read (docs/gr00t-import.md).
    Import(Gr00tImportOptions),
}

/// Options of `pir2 gr00t example`.
#[derive(Debug, Clone, clap::Args)]
pub struct Gr00tExampleOptions {
    /// Output checkpoint directory; must not exist or be empty (nothing is overwritten).
    pub dir: PathBuf,
    /// Seed of the random weights (the same seed writes the same files).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Options of `pir2 gr00t import`.
#[derive(Debug, Clone, clap::Args)]
pub struct Gr00tImportOptions {
    /// The GR00T N1.7 checkpoint directory (e.g. a download of nvidia/GR00T-N1.7-LIBERO's
    /// `libero_10/`).
    pub checkpoint: PathBuf,
    /// Output directory; must not exist or be empty.
    #[arg(long)]
    pub out: PathBuf,
    /// The embodiment (a key of processor_config.json's modality_configs); needed when the
    /// checkpoint has several.
    #[arg(long)]
    pub embodiment_tag: Option<String>,
    /// NVIDIA's ONNX export of this checkpoint (`export_onnx_n1d7.py --export-mode
    /// full_pipeline --output-dir DIR`): its ViT and LLM graphs are imported, bfloat16 ones
    /// rewritten to float32 for ONNX Runtime's CPU provider.
    #[arg(long)]
    pub backbone_onnx: Option<PathBuf>,
    /// With --backbone-onnx: keep bfloat16 graphs as they are (for --ep cuda|tensorrt).
    #[arg(long, requires = "backbone_onnx")]
    pub keep_bf16: bool,
    /// Control rate of the robot, Hz (GR00T's files do not record it).
    #[arg(long, default_value_t = 25.0)]
    pub control_hz: f64,
}

/// Options of `pir2 gr00t export`.
#[derive(Debug, Clone, clap::Args)]
pub struct Gr00tExportOptions {
    /// A `pir2 gr00t train` step directory (model.safetensors + config.json;
    /// statistics.json and embodiment.toml in the run directory above it).
    pub step: PathBuf,
    /// Output GR00T checkpoint directory (docs/gr00t-contract.md: the four action-head
    /// graphs, pir2_gr00t.safetensors, statistics.json, embodiment.toml); must not exist
    /// or be empty.
    #[arg(long)]
    pub out: PathBuf,
}

/// Options of `pir2 gr00t bench`.
#[derive(Debug, Clone, clap::Args)]
pub struct Gr00tBenchOptions {
    /// The export directory (docs/gr00t-contract.md).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// The task (key or prompt) whose prompt layout the head is fed.
    #[arg(long)]
    pub task: String,
    /// Seconds of calls per graph.
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
    /// Where ONNX Runtime runs the graphs.
    #[command(flatten)]
    pub ep: EpOptions,
}

/// Run a `pir2 gr00t` verb. Training and feature extraction stop on SIGINT/SIGTERM
/// ([`crate::signals::stop_flag`]) at a point they resume from.
pub fn gr00t(cmd: Gr00tCmd) -> Result<()> {
    #[cfg(feature = "gr00t")]
    match cmd {
        Gr00tCmd::Features(o) => imp::features(o, crate::signals::stop_flag()),
        Gr00tCmd::Train(o) => imp::train(*o, crate::signals::stop_flag()),
        Gr00tCmd::Export(o) => imp::export(&o),
        Gr00tCmd::Bench(o) => imp::bench(&o),
        Gr00tCmd::Example(o) => imp::example(&o),
        Gr00tCmd::Import(o) => imp::import(&o),
    }
    #[cfg(not(feature = "gr00t"))]
    {
        let verb = match cmd {
            Gr00tCmd::Features(_) => "features",
            Gr00tCmd::Train(_) => "train",
            Gr00tCmd::Export(_) => "export",
            Gr00tCmd::Bench(_) => "bench",
            Gr00tCmd::Example(_) => "example",
            Gr00tCmd::Import(_) => "import",
        };
        anyhow::bail!(
            "`pir2 gr00t {verb}` needs a pir2 built with feature `gr00t` (--features gr00t)"
        )
    }
}

#[cfg(feature = "gr00t")]
mod imp {
    use std::sync::atomic::AtomicBool;
    use std::sync::Arc;

    use anyhow::{Context, Result};

    use super::{Gr00tBenchOptions, Gr00tExampleOptions, Gr00tExportOptions, Gr00tImportOptions};
    use crate::study::gr00t::{self, features, Gr00tFeaturesOptions, Gr00tTrainOptions};

    pub(super) fn train(mut o: Gr00tTrainOptions, stop: Arc<AtomicBool>) -> Result<()> {
        o.stop = Some(stop);
        let steps = o.steps;
        let s = gr00t::train(&o, |p| {
            if p.step % 10 == 0 || p.step == steps {
                eprintln!(
                    "step {}/{}  loss {:.5}  lr {:.2e}",
                    p.step, p.steps, p.loss, p.lr
                );
            }
        })?;
        let (cache, built) = &s.cache;
        println!(
            "VL-token cache: {} ({})",
            cache.display(),
            if *built { "built" } else { "reused" }
        );
        if let Some((step, loss)) = s.report.losses.last() {
            println!("step {step}: loss {loss:.5}");
        }
        for c in &s.report.checkpoints {
            if let Some(d) = &c.dir {
                println!("checkpoint: {}", d.display());
            }
        }
        Ok(())
    }

    pub(super) fn features(mut o: Gr00tFeaturesOptions, stop: Arc<AtomicBool>) -> Result<()> {
        o.stop = Some(stop);
        let mut last = std::time::Instant::now();
        let s = features::extract(&o, |p| {
            if p.done == p.total || last.elapsed().as_secs_f64() >= 2.0 {
                last = std::time::Instant::now();
                let rate = p.this_run as f64 / p.elapsed.max(1e-9);
                let eta = (p.total - p.done) as f64 / rate.max(1e-9);
                eprintln!(
                    "features: {}/{} frames ({:.1} %), episode {}, {:.2} frames/s, {:.0} s left",
                    p.done,
                    p.total,
                    100.0 * p.done as f64 / p.total as f64,
                    p.episode,
                    rate,
                    eta
                );
            }
        })?;
        let (n, t, d) = s.shape;
        println!("backbone: {}", s.backbone);
        println!("decoder: {}", s.decoder);
        if s.resumed_from > 0 {
            println!("resumed at frame {}", s.resumed_from);
        }
        if s.complete {
            println!(
                "features: {} (embeddings [{n}, {t}, {d}], image_mask, attention_mask)",
                s.path.display()
            );
        } else {
            println!(
                "interrupted after {} of {n} frames; {} is kept: run again with --resume",
                s.done,
                s.path.display()
            );
        }
        Ok(())
    }

    pub(super) fn export(o: &Gr00tExportOptions) -> Result<()> {
        let s = gr00t::export(&o.step, &o.out)?;
        println!(
            "wrote {} (H = {}, d_vis_max = {}, trained as {}): {}",
            s.out.display(),
            s.horizon,
            s.d_vis_max,
            s.trained,
            s.files.join(", ")
        );
        println!(
            "add the backbone (onnx/backbone.onnx, or GR00T's split export: \
             onnx/vit_fp32.onnx, onnx/llm_fp32.onnx and the token table's model.safetensors, \
             e.g. from the `pir2 gr00t import` directory) and the VLM's tokenizer.json to run \
             it (docs/gr00t-contract.md)"
        );
        Ok(())
    }

    pub(super) fn bench(o: &Gr00tBenchOptions) -> Result<()> {
        print!(
            "{}",
            crate::bench::gr00t(&o.checkpoint, &o.task, &o.ep, o.seconds)
                .with_context(|| format!("benchmarking {}", o.checkpoint.display()))?
        );
        Ok(())
    }

    pub(super) fn example(o: &Gr00tExampleOptions) -> Result<()> {
        let s = pir2_backends::gr00t::write_example(&o.dir, o.seed)?;
        println!(
            "wrote {} (random weights, seed {}; not GR00T): {}",
            s.dir.display(),
            o.seed,
            s.files.join(", ")
        );
        println!(
            "run it on the emulators: pir2 run gr00t-xarm-xhand --checkpoint {} --task \"catch \
             the book\" --emulate --seconds 2",
            s.dir.display()
        );
        Ok(())
    }

    pub(super) fn import(o: &Gr00tImportOptions) -> Result<()> {
        use pir2_backends::gr00t::import::{import_checkpoint, ImportOptions};
        let s = import_checkpoint(
            &o.checkpoint,
            &o.out,
            &ImportOptions {
                embodiment_tag: o.embodiment_tag.clone(),
                backbone_onnx: o.backbone_onnx.clone(),
                keep_bf16: o.keep_bf16,
                control_hz: o.control_hz,
            },
        )
        .with_context(|| format!("importing {}", o.checkpoint.display()))?;
        println!(
            "wrote {} (embodiment `{}`, slot {}, H = {}, state {} / action {} values, \
             [policy] trained = \"flow\"): {}",
            s.out.display(),
            s.embodiment_tag,
            s.embodiment_id,
            s.horizon,
            s.state_dim,
            s.action_dim,
            s.files.join(", ")
        );
        for (file, r) in &s.converted {
            println!(
                "{file}: bfloat16 → float32 ({} tensors, {} type declarations, {} Cast/dtype \
                 attributes; {} tensors in {})",
                r.tensors,
                r.types,
                r.attributes,
                r.external,
                r.data_file
                    .as_ref()
                    .and_then(|p| p.file_name())
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_else(|| "the protobuf".into())
            );
        }
        if s.missing.is_empty() {
            println!(
                "complete: `pir2 run gr00t-xarm-xhand --checkpoint {}` reads it",
                s.out.display()
            );
        } else {
            println!("before `pir2 run`, add:");
            for m in &s.missing {
                println!("  {}: {}", m.file, m.how);
            }
        }
        Ok(())
    }
}
