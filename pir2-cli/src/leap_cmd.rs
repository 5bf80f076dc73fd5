//! Entry points of `pir2 collect|train|eval|report leap-cube`, compiled with or without the `mujoco`
//! feature: without it each returns one error saying to rebuild with `--features mujoco`, so
//! `main.rs` needs no feature gates. The work itself lives in `crate::leap` (feature `mujoco`).

use std::path::{Path, PathBuf};

use anyhow::Result;

use pir2_sim::dataset::WriteMode;

/// The error every `leap-cube` command gives in a build without the `mujoco` feature.
pub const NEEDS_MUJOCO: &str = "the leap-cube task needs MuJoCo: build with `--features mujoco` \
     (cargo run --release -p pir2-cli --features mujoco -- ...; run `bash scripts/setup-native.sh` \
     and `source .native/env.sh` first)";

/// Options of `pir2 train leap-cube` / `pir2 eval leap-cube`.
#[derive(Debug, Clone, Default)]
pub struct LeapArgs<'a> {
    /// TOML config (fields of `LeapStudyConfig`); defaults when absent.
    pub config: Option<&'a Path>,
    /// Dataset directory (overrides the config's `dataset`).
    pub data: Option<&'a Path>,
    /// Trained policies (overrides the config's `pretrained`).
    pub pretrained: Option<&'a Path>,
    /// Episodes per cell (overrides the config's `episodes`).
    pub episodes: Option<usize>,
    /// Train policies missing from `pretrained` (sets the config's `train_missing`).
    pub train_missing: bool,
}

/// Who demonstrates in `pir2 collect leap-cube`.
#[derive(Debug, Clone, PartialEq)]
pub enum ExpertChoice {
    /// The sampling MPC on the privileged state (`fast`: the cheaper recipe).
    Mpc {
        /// The faster, weaker recipe.
        fast: bool,
    },
    /// Trained policy weights (`pir2-ppo-expert-v1`), used deterministically: one file for
    /// every seed, or one per seed.
    Weights(Vec<PathBuf>),
}

/// `pir2 collect leap-cube`: `per_seed` expert episodes for each of `seeds` into the
/// LeRobotDataset v3.0 at `out` (resumable with [`WriteMode::Resume`]).
pub fn collect(
    out: &Path,
    seeds: &[u64],
    per_seed: usize,
    mode: WriteMode,
    expert: &ExpertChoice,
    stop: &std::sync::atomic::AtomicBool,
) -> Result<()> {
    #[cfg(feature = "mujoco")]
    {
        let t = std::time::Instant::now();
        let s = crate::study::leap_cube::collect_leap(out, seeds, per_seed, mode, expert, stop)?;
        println!(
            "{}: {} episodes, {} frames ({} written now, {:.1} s)",
            out.display(),
            s.total_episodes,
            s.total_frames,
            s.written_episodes,
            t.elapsed().as_secs_f64()
        );
        Ok(())
    }
    #[cfg(not(feature = "mujoco"))]
    {
        let _ = (out, seeds, per_seed, mode, expert, stop);
        anyhow::bail!(NEEDS_MUJOCO)
    }
}

#[cfg(feature = "mujoco")]
fn load_config(args: &LeapArgs) -> Result<crate::study::leap_cube::LeapStudyConfig> {
    use anyhow::Context;
    let mut cfg: crate::study::leap_cube::LeapStudyConfig = match args.config {
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .with_context(|| format!("reading config {}", p.display()))?;
            toml::from_str(&text).with_context(|| format!("parsing config {}", p.display()))?
        }
        None => Default::default(),
    };
    if let Some(d) = args.data {
        cfg.dataset = d.to_string_lossy().into_owned();
    }
    if let Some(d) = args.pretrained {
        cfg.pretrained = Some(d.to_string_lossy().into_owned());
    }
    if let Some(e) = args.episodes {
        cfg.episodes = e;
    }
    cfg.train_missing |= args.train_missing;
    Ok(cfg)
}

/// `pir2 train leap-cube`: train `policies` (the config's `policies` when empty) × the
/// config's seeds into `out`; `resume` continues an interrupted run there.
pub fn train(
    args: &LeapArgs,
    policies: &[pir2_runtime::Policy],
    out: &Path,
    resume: bool,
) -> Result<()> {
    #[cfg(feature = "mujoco")]
    {
        use crate::study::leap_cube;
        let cfg = load_config(args)?;
        let ps = if policies.is_empty() {
            cfg.policies.clone()
        } else {
            policies.to_vec()
        };
        let r = leap_cube::train_policies(&cfg, &ps, out, resume)?;
        for (p, s, scores) in r {
            println!("{p:?} seed {s}: closed-loop validation (step, success) {scores:?}");
        }
        println!(
            "wrote {} (evaluate with `pir2 eval leap-cube --checkpoint {}`)",
            out.display(),
            out.display()
        );
        Ok(())
    }
    #[cfg(not(feature = "mujoco"))]
    {
        let _ = (args, policies, out, resume);
        anyhow::bail!(NEEDS_MUJOCO)
    }
}

/// `pir2 eval leap-cube --study deployment|horizon`: run the study into `out` (a new
/// directory, or with `resume` an interrupted evaluation to continue: `cells.jsonl`,
/// `result.json`, `table.md`, `success.png`) and print its table.
pub fn eval(study: &str, args: &LeapArgs, out: &Path, resume: bool) -> Result<()> {
    #[cfg(feature = "mujoco")]
    {
        let cfg = load_config(args)?;
        let r = match study {
            "deployment" => crate::study::leap_cube::study_deployment(&cfg, out, resume)?,
            "horizon" => crate::study::leap_cube::study_horizon(&cfg, out, resume)?,
            other => anyhow::bail!("unknown study {other} (deployment or horizon)"),
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
    #[cfg(not(feature = "mujoco"))]
    {
        let _ = (study, args, out, resume);
        anyhow::bail!(NEEDS_MUJOCO)
    }
}

/// `pir2 report leap-cube --study deployment|horizon`: the study's tables from the cell log
/// `cells` alone (`crate::study::report`), printed, and with `out` written there
/// (`report.json`, `table.md`, plots); `partial` reports a log that lacks cells.
pub fn report(
    study: &str,
    args: &LeapArgs,
    cells: &Path,
    out: Option<&Path>,
    partial: bool,
) -> Result<()> {
    #[cfg(feature = "mujoco")]
    {
        use crate::study::report;
        let task = crate::study::leap_cube::LeapCubeTask::new(load_config(args)?)?;
        let s = match study {
            "deployment" => task.deployment_study(),
            "horizon" => task.horizon_study(),
            other => anyhow::bail!("unknown study {other} (deployment or horizon)"),
        };
        let r = report::report(&task, &s, cells, partial)?;
        println!(
            "\nLeap cube, {} study from {} ({} episodes per cell, config {}):\n\n{}",
            r.study,
            cells.display(),
            r.config.episodes,
            r.fingerprint,
            r.table()
        );
        if let Some(out) = out {
            report::write_report(&task, &r, &s.x_label, out)?;
            println!("wrote {}/report.json, table.md, success.png", out.display());
        }
        Ok(())
    }
    #[cfg(not(feature = "mujoco"))]
    {
        let _ = (study, args, cells, out, partial);
        anyhow::bail!(NEEDS_MUJOCO)
    }
}
