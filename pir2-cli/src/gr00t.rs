//! `pir2 gr00t <verb>`: the GR00T N1.7 commands (feature `gr00t`; a build without it offers
//! the same verbs and options, and each says how to build it). The work is
//! [`crate::study::gr00t`]'s, `crate::bench::gr00t`'s, [`crate::run`]'s (`run`) and
//! [`crate::serve`]'s (`serve`); this module prints what a user reads, and maps the old
//! spellings of `run` and `serve` to these ([`new_spelling`]).

use std::ffi::OsString;
use std::path::PathBuf;

use anyhow::Result;

use crate::ep::EpOptions;
use crate::run::RunOptions;
use crate::serve::Gr00tServeCmd;
use crate::study::gr00t::{Gr00tFeaturesOptions, Gr00tTrainOptions};

/// The verbs of `pir2 gr00t`.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum Gr00tCmd {
    /// Precompute GR00T N1.7's frozen backbone features (the checkpoint's ONNX backbone and
    /// tokenizer, run as `pir2 gr00t run` runs them) on every frame of a LeRobotDataset v3.0,
    /// written as the `--features` file of `pir2 gr00t train` (needs the `ffmpeg` program for
    /// video cameras).
    Features(Gr00tFeaturesOptions),
    /// πR² fine-tuning of a GR00T N1.7 checkpoint's action head on a dataset and its
    /// precomputed backbone features, with candle.
    Train(Box<Gr00tTrainOptions>),
    /// A `pir2 gr00t train` step directory to the GR00T checkpoint layout
    /// (docs/gr00t-contract.md), which `pir2 gr00t run` runs.
    Export(Gr00tExportOptions),
    /// One-NFE latency of a GR00T export's action head and backbone, and the delay `d` it
    /// implies; with `--train`, the time of one `pir2 gr00t train` step of a checkpoint's
    /// head at a given batch (default: the paper's 512) on a synthetic batch.
    Bench(Gr00tBenchOptions),
    /// Write a small example checkpoint with random weights (the xArm6 + XHand embodiment,
    /// N1.7's shapes at tiny widths: action head, stand-in backbone, tokenizer) that
    /// `pir2 gr00t run gr00t-xarm-xhand --emulate` runs; no download, no Python.
    Example(Gr00tExampleOptions),
    /// A GR00T N1.7 checkpoint as Isaac-GR00T writes it (config.json, safetensors,
    /// processor_config.json, statistics.json, embodiment_id.json) to the checkpoint layout
    /// `pir2 gr00t run` and `pir2 gr00t train` read (docs/gr00t-import.md).
    Import(Gr00tImportOptions),
    /// Run a GR00T stack on a robot (or its emulators): the action head one NFE per control
    /// tick, the backbone on the slow channel, each here or on `pir2 gr00t serve`.
    Run(Box<RunOptions>),
    /// Servers for a GR00T run's remote action head and remote backbone (feature `remote`).
    Serve {
        #[command(subcommand)]
        cmd: Gr00tServeCmd,
    },
}

/// The arguments of a command line (program name first) in the current spelling, and the
/// note to print on stderr when they used an old one: `pir2 run STACK …` is
/// `pir2 gr00t run STACK …`, and `pir2 serve policy|slow … --gr00t-checkpoint DIR …` is
/// `pir2 gr00t serve policy|slow … --checkpoint DIR …` (which still takes
/// `--gr00t-checkpoint` under its old name). Other command lines are returned unchanged.
pub fn new_spelling(mut args: Vec<OsString>) -> (Vec<OsString>, Option<String>) {
    let is = |i: usize, s: &str| args.get(i).is_some_and(|a| a == s);
    let note = if is(1, "run") {
        "note: `pir2 run` is now `pir2 gr00t run` (the old spelling will go)".to_string()
    } else if is(1, "serve")
        && (is(2, "policy") || is(2, "slow"))
        && args.iter().skip(3).any(|a| {
            let a = a.to_string_lossy();
            a == "--gr00t-checkpoint" || a.starts_with("--gr00t-checkpoint=")
        })
    {
        let verb = args[2].to_string_lossy().into_owned();
        format!(
            "note: `pir2 serve {verb} --gr00t-checkpoint` is now `pir2 gr00t serve {verb} \
             --checkpoint` (the old spelling will go)"
        )
    } else {
        return (args, None);
    };
    args.insert(1, "gr00t".into());
    (args, Some(note))
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
    /// What the head was fine-tuned as, written as `[policy] trained`: pi_r2, pi_r2_hidden,
    /// pi_r2_full, pi_r2_zero_delay, pi_r2_zero_delay_full, rtc or flow (default: pi_r2 for
    /// a head with per-position AdaLN heads `<layer>_heads.*`, flow for one without). A head
    /// with per-position heads is refused as flow or rtc.
    #[arg(long)]
    pub trained: Option<String>,
    /// πR² NFEs per action (`[policy] nfe`; default 2, or the largest n πR²'s staircase
    /// allows at the imported H and d_max when smaller); must fit that staircase.
    #[arg(long)]
    pub nfe: Option<usize>,
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
///
/// Without `--train`: the one-NFE latency of an export's ONNX graphs (`--checkpoint EXPORT
/// --task T [--seconds S] [--ep EP]`). With `--train`: the wall-clock time of one
/// `pir2 gr00t train` step (batch draw, upload, forward with GR00T's dropout, loss, backward,
/// grad-norm clip, AdamW) on a synthetic seeded batch of the head's real shapes
/// (`--checkpoint HEAD [--batch 512] [--steps N] [--warmup K] [--device D] [--json FILE]`).
#[derive(Debug, Clone, clap::Args)]
pub struct Gr00tBenchOptions {
    /// The export directory (docs/gr00t-contract.md); with --train, a checkpoint
    /// `pir2 gr00t train` takes (config.json + model.safetensors: a GR00T N1.7 directory,
    /// `pir2 gr00t example`'s `head/`, a training step directory).
    #[arg(long)]
    pub checkpoint: PathBuf,
    /// The task (key or prompt) whose prompt layout the head is fed.
    #[arg(long, required_unless_present = "train")]
    pub task: Option<String>,
    /// Seconds of calls per graph.
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
    /// Where ONNX Runtime runs the graphs.
    #[command(flatten)]
    pub ep: EpOptions,
    /// Time training steps of the candle head instead of the ONNX graphs' inference.
    #[arg(long, conflicts_with_all = ["task", "seconds", "ep", "ep_device", "trt_cache"])]
    pub train: bool,
    /// --train: samples per step (the paper's batch: 512).
    #[arg(long, default_value_t = 512, requires = "train")]
    pub batch: usize,
    /// --train: timed steps.
    #[arg(long, default_value_t = 10, requires = "train")]
    pub steps: usize,
    /// --train: untimed steps before them.
    #[arg(long, default_value_t = 2, requires = "train")]
    pub warmup: usize,
    /// --train: the candle device, `cpu`, `cuda[:N]` (a build with `--features cuda`) or
    /// `metal[:N]` (`--features metal`); a GPU the build lacks is an error, never the CPU.
    #[arg(long, default_value = "cpu", requires = "train")]
    pub device: String,
    /// --train: seed of the synthetic batch and of the draws.
    #[arg(long, default_value_t = 0, requires = "train")]
    pub seed: u64,
    /// --train: the embodiment file (default: embodiment.toml in the checkpoint directory or
    /// the one above it).
    #[arg(long, requires = "train")]
    pub embodiment: Option<PathBuf>,
    /// --train: VL tokens per sample (default: the embodiment's prompt.image_tokens +
    /// prompt.text_tokens, the backbone's sequence).
    #[arg(long, requires = "train")]
    pub vl_tokens: Option<usize>,
    /// --train: without GR00T's DiT dropout (as `pir2 gr00t train --no-dropout`).
    #[arg(long = "no-dropout", action = clap::ArgAction::SetFalse, requires = "train")]
    pub dropout: bool,
    /// --train: also write the measurement to this JSON file.
    #[arg(long, requires = "train")]
    pub json: Option<PathBuf>,
}

/// Run a `pir2 gr00t` verb. Training, feature extraction, runs and servers stop on
/// SIGINT/SIGTERM ([`crate::signals::stop_flag`]); training and feature extraction at a point
/// they resume from.
pub fn gr00t(cmd: Gr00tCmd) -> Result<()> {
    #[cfg(not(feature = "gr00t"))]
    let no_gr00t = |verb: &str| -> Result<()> {
        anyhow::bail!(
            "`pir2 gr00t {verb}` needs a pir2 built with feature `gr00t` (--features gr00t)"
        )
    };
    match cmd {
        // `run` and `serve` say themselves what a build without `gr00t` or `remote` lacks
        // (and a failed run writes its `--json` report in any build).
        Gr00tCmd::Run(o) => crate::run::run_command(&o, crate::signals::stop_flag()),
        Gr00tCmd::Serve { cmd } => crate::serve::serve_gr00t(&cmd, crate::signals::stop_flag()),
        #[cfg(feature = "gr00t")]
        Gr00tCmd::Features(o) => imp::features(o, crate::signals::stop_flag()),
        #[cfg(feature = "gr00t")]
        Gr00tCmd::Train(o) => imp::train(*o, crate::signals::stop_flag()),
        #[cfg(feature = "gr00t")]
        Gr00tCmd::Export(o) => imp::export(&o),
        #[cfg(feature = "gr00t")]
        Gr00tCmd::Bench(o) => imp::bench(&o),
        #[cfg(feature = "gr00t")]
        Gr00tCmd::Example(o) => imp::example(&o),
        #[cfg(feature = "gr00t")]
        Gr00tCmd::Import(o) => imp::import(&o),
        #[cfg(not(feature = "gr00t"))]
        Gr00tCmd::Features(_) => no_gr00t("features"),
        #[cfg(not(feature = "gr00t"))]
        Gr00tCmd::Train(_) => no_gr00t("train"),
        #[cfg(not(feature = "gr00t"))]
        Gr00tCmd::Export(_) => no_gr00t("export"),
        #[cfg(not(feature = "gr00t"))]
        Gr00tCmd::Bench(_) => no_gr00t("bench"),
        #[cfg(not(feature = "gr00t"))]
        Gr00tCmd::Example(_) => no_gr00t("example"),
        #[cfg(not(feature = "gr00t"))]
        Gr00tCmd::Import(_) => no_gr00t("import"),
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
        if o.train {
            return bench_train(o);
        }
        let task = o
            .task
            .as_deref()
            .context("--task is required without --train")?;
        print!(
            "{}",
            crate::bench::gr00t(&o.checkpoint, task, &o.ep, o.seconds)
                .with_context(|| format!("benchmarking {}", o.checkpoint.display()))?
        );
        Ok(())
    }

    fn bench_train(o: &Gr00tBenchOptions) -> Result<()> {
        let r = gr00t::bench_train(o)?;
        println!(
            "gr00t train step: {} on {}, batch {}, H {}, A {}, VL tokens {} x {}, {} parameters, \
             dropout {}",
            r.checkpoint.display(),
            r.device,
            r.batch,
            r.horizon,
            r.action_dim,
            r.vl_tokens,
            r.vl_dim,
            r.parameters,
            if r.dropout { "on" } else { "off" }
        );
        println!(
            "  {} timed steps after {} warm-up: median {:.1} ms, p90 {:.1} ms, {:.1} samples/s",
            r.steps, r.warmup, r.median_ms, r.p90_ms, r.samples_per_s
        );
        if let Some(path) = &o.json {
            std::fs::write(path, serde_json::to_string_pretty(&r)?)
                .with_context(|| format!("writing {}", path.display()))?;
        }
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
            "run it on the emulators: pir2 gr00t run gr00t-xarm-xhand --checkpoint {} --task \
             \"catch the book\" --emulate --seconds 2",
            s.dir.display()
        );
        Ok(())
    }

    pub(super) fn import(o: &Gr00tImportOptions) -> Result<()> {
        use pir2_backends::gr00t::config::policy_name;
        use pir2_backends::gr00t::import::{import_checkpoint, ImportOptions};
        let trained = match &o.trained {
            None => None,
            Some(t) => {
                let all = pir2_runtime::Policy::ALL;
                match all.iter().find(|p| policy_name(**p) == *t) {
                    Some(p) => Some(*p),
                    None => {
                        let names: Vec<String> = all.iter().map(|p| policy_name(*p)).collect();
                        anyhow::bail!("--trained {t}: not one of {}", names.join(", "))
                    }
                }
            }
        };
        let s = import_checkpoint(
            &o.checkpoint,
            &o.out,
            &ImportOptions {
                embodiment_tag: o.embodiment_tag.clone(),
                backbone_onnx: o.backbone_onnx.clone(),
                keep_bf16: o.keep_bf16,
                control_hz: o.control_hz,
                trained,
                nfe: o.nfe,
            },
        )
        .with_context(|| format!("importing {}", o.checkpoint.display()))?;
        println!(
            "wrote {} (embodiment `{}`, slot {}, H = {}, state {} / action {} values, \
             {} AdaLN heads, [policy] trained = \"{}\", mode = \"{}\", nfe = {}): {}",
            s.out.display(),
            s.embodiment_tag,
            s.embodiment_id,
            s.horizon,
            s.state_dim,
            s.action_dim,
            if s.position_heads {
                "per-position"
            } else {
                "shared"
            },
            s.trained,
            s.mode,
            s.nfe,
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
                "complete: `pir2 gr00t run gr00t-xarm-xhand --checkpoint {}` reads it",
                s.out.display()
            );
        } else {
            println!("before `pir2 gr00t run`, add:");
            for m in &s.missing {
                println!("  {}: {}", m.file, m.how);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::new_spelling;
    use std::ffi::OsString;

    fn args(line: &str) -> Vec<OsString> {
        line.split(' ').map(OsString::from).collect()
    }

    #[test]
    fn the_old_spellings_become_the_gr00t_verbs_with_a_note() {
        let (a, note) = new_spelling(args("pir2 run gr00t-xarm-xhand --emulate"));
        assert_eq!(a, args("pir2 gr00t run gr00t-xarm-xhand --emulate"));
        assert!(note.unwrap().contains("`pir2 gr00t run`"));
        for verb in ["policy", "slow"] {
            for flag in ["--gr00t-checkpoint ck", "--gr00t-checkpoint=ck"] {
                let (a, note) = new_spelling(args(&format!("pir2 serve {verb} --task t {flag}")));
                assert_eq!(a, args(&format!("pir2 gr00t serve {verb} --task t {flag}")));
                assert!(note.unwrap().contains(&format!("`pir2 gr00t serve {verb}")));
            }
        }
    }

    #[test]
    fn other_command_lines_are_unchanged() {
        for line in [
            "pir2",
            "pir2 serve policy --checkpoint ck",
            "pir2 serve slow --stub 4",
            "pir2 serve",
            "pir2 gr00t run gr00t-xarm-xhand --checkpoint ck",
            "pir2 gr00t serve policy --checkpoint ck --task t",
            "pir2 eval ball-plate --checkpoint run",
        ] {
            let (a, note) = new_spelling(args(line));
            assert_eq!(a, args(line));
            assert!(note.is_none(), "{line}");
        }
    }
}
