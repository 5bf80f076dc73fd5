//! `pir2 collect|train|eval|report leap-cube` (feature `mujoco`; a build without it lists the
//! task with the error [`super::NEEDS_MUJOCO`]). The work itself is
//! [`crate::study::leap_cube`]'s.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use anyhow::{bail, Context, Result};

use super::{CollectOptions, EvalOptions, ReportOptions, TaskCommands, TrainOptions};
use crate::study::leap_cube::{self, ExpertChoice, LeapCubeTask, LeapStudyConfig};
use crate::study::pipeline::select_seeds;
use crate::study::report;

/// The Leap-hand cube task's commands.
#[derive(Debug, Clone, Copy)]
pub struct LeapCube;

/// What the commands override in a `LeapStudyConfig`.
#[derive(Debug, Clone, Default)]
struct Overrides<'a> {
    /// TOML config (fields of `LeapStudyConfig`); defaults when absent.
    config: Option<&'a Path>,
    /// Dataset directory (overrides the config's `dataset`).
    data: Option<&'a Path>,
    /// Trained policies (overrides the config's `pretrained`).
    pretrained: Option<&'a Path>,
    /// Episodes per cell (overrides the config's `episodes`).
    episodes: Option<usize>,
    /// Train policies missing from `pretrained` (sets the config's `train_missing`).
    train_missing: bool,
}

impl Overrides<'_> {
    /// The config file (or the defaults) with these overrides.
    fn load(&self) -> Result<LeapStudyConfig> {
        let mut cfg: LeapStudyConfig = match self.config {
            Some(p) => {
                let text = std::fs::read_to_string(p)
                    .with_context(|| format!("reading config {}", p.display()))?;
                toml::from_str(&text).with_context(|| format!("parsing config {}", p.display()))?
            }
            None => Default::default(),
        };
        if let Some(d) = self.data {
            cfg.dataset = d.to_string_lossy().into_owned();
        }
        if let Some(d) = self.pretrained {
            cfg.pretrained = Some(d.to_string_lossy().into_owned());
        }
        if let Some(e) = self.episodes {
            cfg.episodes = e;
        }
        cfg.train_missing |= self.train_missing;
        Ok(cfg)
    }
}

impl TaskCommands for LeapCube {
    /// `per_seed` expert episodes for each of `--seeds` (resumable with `--resume`).
    fn collect(&self, o: &CollectOptions, stop: &AtomicBool) -> Result<()> {
        let expert = if o.expert.is_empty() {
            ExpertChoice::Mpc { fast: o.fast }
        } else {
            ExpertChoice::Weights(o.expert.clone())
        };
        let t = std::time::Instant::now();
        let s =
            leap_cube::collect_leap(&o.out, &o.seeds, o.per_seed, o.write_mode(), &expert, stop)?;
        super::report_set_aside(&s);
        println!(
            "{}: {} episodes, {} frames ({} written now, {:.1} s)",
            o.out.display(),
            s.total_episodes,
            s.total_frames,
            s.written_episodes,
            t.elapsed().as_secs_f64()
        );
        Ok(())
    }

    /// `--policy` (the config's `policies` when absent) × `--seeds` (the config's seeds when
    /// absent) into `--out`; `--resume` continues an interrupted run there.
    fn train(&self, o: &TrainOptions) -> Result<()> {
        let cfg = Overrides {
            config: o.config.as_deref(),
            data: Some(&o.data),
            ..Default::default()
        }
        .load()?;
        let policies = match o.policy {
            Some(p) => vec![p],
            None => cfg.policies.clone(),
        };
        let r = leap_cube::train_policies(&cfg, &policies, o.seeds.as_deref(), &o.out, o.resume)?;
        for (p, s, scores) in r {
            println!("{p:?} seed {s}: closed-loop validation (step, success) {scores:?}");
        }
        println!(
            "wrote {} (evaluate with `pir2 eval leap-cube --checkpoint {}`)",
            o.out.display(),
            o.out.display()
        );
        Ok(())
    }

    /// The deployment or horizon study into `--out` (a new directory, or with `--resume` an
    /// interrupted evaluation to continue: `cells.jsonl`, `result.json`, `table.md`,
    /// `success.png`); prints its table.
    fn eval(&self, o: &EvalOptions) -> Result<()> {
        let out = o
            .out
            .as_deref()
            .context("--out is required for leap-cube")?;
        let mut cfg = Overrides {
            config: o.config.as_deref(),
            data: o.data.as_deref(),
            pretrained: o.checkpoint.as_deref(),
            episodes: o.episodes,
            train_missing: o.train_missing,
        }
        .load()?;
        if !o.policies.is_empty() {
            cfg.policies = o.policies.clone();
        }
        cfg.seeds = select_seeds(&cfg.seeds, o.seeds.as_deref())?;
        if let Some(k) = o.best_of_last {
            cfg.best_of_last = k;
        }
        let r = match o.study.as_str() {
            "deployment" => leap_cube::study_deployment(&cfg, out, o.resume)?,
            "horizon" => leap_cube::study_horizon(&cfg, out, o.resume)?,
            other => bail!("unknown study {other} (deployment or horizon)"),
        };
        println!(
            "\nLeap cube, {} study ({} demos, {} episodes per cell, seeds {:?}):\n\n{}",
            r.study,
            r.demos,
            r.config.episodes,
            r.config.seeds,
            r.table()
        );
        for (stage, s) in &r.timings {
            println!("{stage:>9}: {s:7.1} s");
        }
        println!("wrote {}/result.json, table.md, success.png", out.display());
        Ok(())
    }

    /// The study's tables from the cell log `--cells` alone ([`crate::study::report`]),
    /// printed, and with `--out` written there (`report.json`, `table.md`, plots);
    /// `--partial` reports a log that lacks cells.
    fn report(&self, o: &ReportOptions) -> Result<()> {
        let cfg = Overrides {
            config: o.config.as_deref(),
            data: o.data.as_deref(),
            ..Default::default()
        }
        .load()?;
        let task = LeapCubeTask::new(cfg)?;
        let s = match o.study.as_str() {
            "deployment" => task.deployment_study(),
            "horizon" => task.horizon_study(),
            other => bail!("unknown study {other} (deployment or horizon)"),
        };
        let logs: Vec<&Path> = o.cells.iter().map(PathBuf::as_path).collect();
        let r = report::report(&task, &s, &logs, o.partial)?;
        println!(
            "\nLeap cube, {} study from {} ({} episodes per cell, config {}):\n\n{}",
            r.study,
            logs.iter()
                .map(|l| l.display().to_string())
                .collect::<Vec<_>>()
                .join(" + "),
            r.config.episodes,
            r.fingerprint,
            r.table()
        );
        if let Some(out) = &o.out {
            report::write_report(&task, &r, &s.x_label, out)?;
            println!("wrote {}/report.json, table.md, success.png", out.display());
        }
        Ok(())
    }
}
