//! `pir2 collect|train|eval ballplate`: the embedded ball-on-plate task (candle MLPs, one
//! policy per `pir2 train`, a checkpoint evaluated locally or through a policy server).

use std::sync::atomic::AtomicBool;
use std::time::Duration;

use anyhow::{bail, Context, Result};

use pir2_backends::candle::CandleModel;
use pir2_runtime::Policy;

use super::{CollectOptions, EvalOptions, ReportOptions, TaskCommands, TrainOptions};
use crate::onnx_checkpoint::{CheckpointKind, OnnxCheckpoint};
use crate::study::ballplate::{self, DemoConfig};
use crate::study::pipeline::Models;

/// The ball-on-plate task's commands.
#[derive(Debug, Clone, Copy)]
pub struct BallPlate;

impl TaskCommands for BallPlate {
    fn collect(&self, o: &CollectOptions, stop: &AtomicBool) -> Result<()> {
        let (stats, summary) =
            ballplate::collect_into(&o.out, o.episodes, o.seed, o.write_mode(), stop)?;
        super::report_set_aside(&summary);
        if stats.stopped {
            println!(
                "interrupted: {} holds {} of {} episodes ({} written now); \
                 `pir2 collect --resume` adds the rest",
                o.out.display(),
                summary.total_episodes,
                o.episodes,
                summary.written_episodes
            );
        } else {
            println!(
                "wrote {} episodes to {}",
                summary.written_episodes,
                o.out.display()
            );
        }
        Ok(())
    }

    fn train(&self, o: &TrainOptions) -> Result<()> {
        let policy = o.policy.context("--policy is required for ballplate")?;
        if !super::BALLPLATE_POLICIES.contains(&policy) {
            let names: Vec<&str> = super::BALLPLATE_POLICIES.map(Policy::name).to_vec();
            bail!(
                "--policy {}: ballplate trains {}",
                policy.name(),
                names.join(", ")
            );
        }
        let cfg = DemoConfig::load(o.config.as_deref(), false)?;
        let scores = ballplate::train_checkpoint(&o.data, policy, &cfg, o.seed, &o.out, o.resume)
            .map_err(|e| {
            let config = o
                .config
                .as_ref()
                .map(|c| format!(" --config {}", c.display()))
                .unwrap_or_default();
            super::with_resume_hint(
                e,
                &format!(
                    "pir2 train ballplate --data {} --policy {} --seed {}{config} \
                             --out {} --resume",
                    o.data.display(),
                    policy.name(),
                    o.seed,
                    o.out.display()
                ),
            )
        })?;
        println!("closed-loop validation (step, success): {scores:?}");
        println!("best checkpoint: {}", o.out.join("best").display());
        Ok(())
    }

    /// A checkpoint in every mode that fits it at each unit delay, locally or through a
    /// policy server (`--remote`).
    fn eval(&self, o: &EvalOptions) -> Result<()> {
        let checkpoint = o
            .checkpoint
            .as_deref()
            .context("--checkpoint is required for ballplate")?;
        let policy = o.policy.context("--policy is required for ballplate")?;
        if !o.policies.is_empty() {
            bail!("--policies narrows a leap-cube study; ballplate evaluates one checkpoint, named by --policy");
        }
        if o.best_of_last.is_some() {
            bail!("--best-of-last applies to a leap-cube study's runs; ballplate evaluates one checkpoint");
        }
        if let Some(p) = o.json.as_ref().filter(|p| p.exists()) {
            bail!("{} already exists; choose another --json path", p.display());
        }
        let episodes = o.episodes.unwrap_or(100);
        if crate::onnx_checkpoint::kind(checkpoint)? == CheckpointKind::Onnx {
            // An ONNX checkpoint (e.g. trained in PyTorch): run through ONNX Runtime.
            if o.remote.is_some() {
                bail!(
                    "--remote evaluates a candle checkpoint served by `pir2 serve policy`; {} \
                     is an ONNX checkpoint, evaluated locally only",
                    checkpoint.display()
                );
            }
            let ck = OnnxCheckpoint::read(checkpoint, &ballplate::spec())?;
            crate::identity::expect_trained_as(ck.policy(), checkpoint, policy, "--policy")?;
            let models = ck.models(&ballplate::spec())?;
            eprintln!(
                "evaluating ONNX checkpoint {} through ONNX Runtime",
                checkpoint.display()
            );
            let (cells, labels) =
                ballplate::eval_checkpoint(&models, policy, &o.d0, episodes, o.seed)?;
            return report_cells(o, &cells, &labels);
        }
        let model = CandleModel::load(checkpoint)
            .with_context(|| format!("loading {}", checkpoint.display()))?;
        crate::identity::expect_policy(&model, checkpoint, policy, "--policy")?;
        let (cells, labels) = match &o.remote {
            None => {
                let models = Models::local(&model)?;
                ballplate::eval_checkpoint(&models, policy, &o.d0, episodes, o.seed)?
            }
            Some(endpoint) => {
                let remote = crate::remote::RemotePolicy::connect(
                    endpoint,
                    &o.tls,
                    Duration::from_millis(o.remote_timeout_ms.max(1)),
                    Duration::from_secs_f64(o.connect_timeout.max(0.0)),
                    o.remote_max_failed.max(1),
                )?;
                eprintln!("connected to the policy server at {endpoint}");
                remote.expect_checkpoint(&model, checkpoint, policy)?;
                let models = remote.models(&model);
                let res = ballplate::eval_checkpoint(&models, policy, &o.d0, episodes, o.seed)
                    .with_context(|| remote.context());
                eprintln!("{}", remote.report());
                res?
            }
        };
        report_cells(o, &cells, &labels)
    }

    fn report(&self, _: &ReportOptions) -> Result<()> {
        bail!("ballplate keeps no cell log: `pir2 report` is for leap-cube studies")
    }
}

/// Print the evaluation table and write the cells to `--json`.
fn report_cells(o: &EvalOptions, cells: &[crate::study::Cell], labels: &[String]) -> Result<()> {
    println!("{}", crate::study::table(cells, labels, &o.d0));
    if let Some(p) = &o.json {
        std::fs::write(p, serde_json::to_string_pretty(cells)?)?;
    }
    Ok(())
}
