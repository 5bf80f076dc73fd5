//! Evaluation of a study: every row × seed × column through the one closed loop, the paper's
//! best-checkpoint-per-cell protocol, and the cell log that lets a long evaluation continue
//! after an interruption (`pir2 eval … --resume`).
//!
//! One file on purpose: the cell log's key and the evaluation that fills it must agree bit for
//! bit (a cell is reused only when it would measure the same numbers), so they are read
//! together; a third of the file is their tests.
//!
//! A cell's result depends on the checkpoint that ran, the row, the column, the seed, the
//! episode count, the task's config and the evaluation path, nothing else (the lock-step
//! evaluation is deterministic and independent of the thread count; a batched cell, see
//! [`EvalPath`], also depends on its group size and kernel thread count, and is tagged with
//! them). [`CellLog`] keys the cells it keeps by exactly that, so a later run reuses a cell only when it would measure the same numbers;
//! which policies, seeds and columns the config lists, its checkpoint-protocol depth and its
//! thread count are not part of the key, which is what lets a one-seed table of some policies
//! grow into the full three-seed one without measuring a cell twice.

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use anyhow::{bail, Context, Result};
use indicatif::ProgressBar;
use serde::{Deserialize, Serialize};

use pir2_backends::candle::CandleModel;
use pir2_runtime::{LockstepTiming, Mode};

use super::closed_loop::{closed_loop, EvalPath, Models, Trained};
use super::output::{log_line, write_atomically};
use super::report::task_checkpoint_steps;
use super::{Cell, Policy, Study, Sweep, Task};

/// File of the cell log inside a study's output directory.
pub const CELL_LOG: &str = "cells.jsonl";

/// Config fields a cell does not depend on (left out of [`config_fingerprint`]): which
/// policies, seeds and columns are evaluated (the key names the cell's own), the
/// best-of-last depth, whether the diagnostic rows are added, the thread count, the
/// batched-evaluation group (which goes into each cell's key instead), and where the trained
/// policies are read from and whether missing ones may be trained (the weights' hash in each
/// key names the checkpoint that ran, wherever it lies).
const NOT_IN_FINGERPRINT: [&str; 10] = [
    "policies",
    "seeds",
    "d0s",
    "hs",
    "best_of_last",
    "threads",
    "batch_episodes",
    "diagnostic_rows",
    "pretrained",
    "train_missing",
];

/// Fields of [`NOT_IN_FINGERPRINT`] that earlier versions hashed: `pretrained` (the
/// `--checkpoint` path) until cell logs stopped depending on where the checkpoints lie.
/// `train_missing` did not exist then, so it is left out of the earlier fingerprint too.
const HASHED_BEFORE: [&str; 1] = ["pretrained"];

/// Fields added after cells were logged, with the value every config of before implied: a
/// config holding that value leaves the field out of its fingerprint, so the cells measured
/// then keep matching it. `pir2_film`: the πR² U-Nets were the shared-projection ablation
/// until the paper's per-position heads became the default.
const IMPLIED_BEFORE: [(&str, &str); 1] = [("pir2_film", "per_position_tau")];

/// A short, stable fingerprint of what in `config` a cell depends on: the config as TOML
/// without the fields in `NOT_IN_FINGERPRINT` (and those of `IMPLIED_BEFORE` holding their
/// implied value), hashed (FNV-1a, 64 bits).
pub fn config_fingerprint<C: Serialize>(config: &C) -> Result<String> {
    fingerprint_without(config, |k| NOT_IN_FINGERPRINT.contains(&k))
}

/// The fingerprints earlier versions of pir2 gave `config` where they differ from
/// [`config_fingerprint`]: cells logged under them were measured with this config and are
/// reused ([`CellLog::open`]). One today: the fingerprint that still hashed the
/// `--checkpoint` path (`pretrained`), so a log written before matches only when resumed
/// with the same path.
pub fn earlier_config_fingerprints<C: Serialize>(config: &C) -> Result<Vec<String>> {
    let now = config_fingerprint(config)?;
    let before = fingerprint_without(config, |k| {
        NOT_IN_FINGERPRINT.contains(&k) && !HASHED_BEFORE.contains(&k)
    })?;
    Ok(if before == now {
        Vec::new()
    } else {
        vec![before]
    })
}

/// The config as TOML without the top-level fields `skip` names, hashed (FNV-1a, 64 bits).
fn fingerprint_without<C: Serialize>(config: &C, skip: impl Fn(&str) -> bool) -> Result<String> {
    let mut v = toml::Value::try_from(config).context("serialising the config")?;
    if let Some(t) = v.as_table_mut() {
        let skipped: Vec<String> = t
            .iter()
            .filter(|(k, v)| {
                skip(k)
                    || IMPLIED_BEFORE
                        .iter()
                        .any(|(f, val)| f == k && v.as_str() == Some(val))
            })
            .map(|(k, _)| k.clone())
            .collect();
        for k in skipped {
            t.remove(&k);
        }
    }
    let text = toml::to_string(&v).context("serialising the config")?;
    Ok(format!("{:016x}", fnv1a(FNV_OFFSET, text.as_bytes())))
}

/// FNV-1a (64 bits) offset basis.
pub(crate) const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;

/// FNV-1a (64 bits) of `bytes`, continuing from `h` ([`FNV_OFFSET`] to start).
pub(crate) fn fnv1a(mut h: u64, bytes: &[u8]) -> u64 {
    for &b in bytes {
        h = (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
    }
    h
}

/// `#w<hash of the weights file>` for the checkpoint directory `dir`, empty when it has no
/// readable `model.safetensors`. Part of a cell's checkpoint key, so that a cell measured on
/// one set of weights is never taken for another checkpoint of the same name and step: a
/// run retrained on other data, or on a machine whose SIMD kernels round differently,
/// writes other weights under the same `…/best@14000`.
fn weights_tag(dir: &Path) -> String {
    std::fs::read(dir.join("model.safetensors"))
        .map(|b| format!("#w{:016x}", fnv1a(FNV_OFFSET, &b)))
        .unwrap_or_default()
}

/// What identifies a measured cell besides the config.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub(crate) struct CellKey {
    /// The checkpoint that ran (see [`chosen_checkpoint`]).
    pub(crate) checkpoint: String,
    pub(crate) label: String,
    /// The column; `None` for a row measured once for every column.
    pub(crate) column: Option<usize>,
    pub(crate) seed: u64,
    pub(crate) episodes: usize,
    /// How the cell ran when not batch-1 ([`EvalPath::cell_tag`]); absent for batch-1 cells,
    /// so logs written before batched evaluation existed keep their keys.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) eval: Option<String>,
}

/// One line of the cell log.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct Entry {
    pub(crate) config: String,
    #[serde(flatten)]
    pub(crate) key: CellKey,
    pub(crate) successes: usize,
    pub(crate) overruns: u64,
}

/// The cells of the log text `text` (read from `path`), each with its line, and whether a
/// last line cut short by an interruption (only ever the last line, and only without its
/// newline) was left out. Any other line that is not a cell is an error naming it.
pub(crate) fn parse_log<'t>(text: &'t str, path: &Path) -> Result<(Vec<(Entry, &'t str)>, bool)> {
    let lines: Vec<&str> = text.split_terminator('\n').collect();
    let mut entries = Vec::with_capacity(lines.len());
    for (i, line) in lines.iter().enumerate() {
        match serde_json::from_str::<Entry>(line) {
            Ok(e) => entries.push((e, *line)),
            Err(_) if i + 1 == lines.len() && !text.ends_with('\n') => return Ok((entries, true)),
            Err(e) => bail!("{} line {}: not a study cell: {e}", path.display(), i + 1),
        }
    }
    Ok((entries, false))
}

/// The cells a study's evaluation measured so far, kept in `out/cells.jsonl` (one JSON line
/// per cell, appended and synced as soon as the cell is measured). Opened with `resume`, the
/// cells of an earlier, interrupted run of the same config are reused instead of measured
/// again. With a stop flag ([`CellLog::stop_on`]), an evaluation through the log ends
/// before it measures another cell once the flag is set.
#[derive(Debug)]
pub struct CellLog {
    path: PathBuf,
    config: String,
    done: Mutex<HashMap<CellKey, (usize, u64)>>,
    stop: Option<Arc<AtomicBool>>,
}

impl CellLog {
    /// The log of the study output directory `out` for a config with fingerprint `config`
    /// ([`config_fingerprint`]; `earlier`: the fingerprints earlier versions gave the same
    /// config, [`earlier_config_fingerprints`]). Without `resume` the log starts empty (an
    /// existing one is an error: the caller refuses non-empty directories first). With
    /// `resume`, the cells in the log are loaded, those logged under an `earlier`
    /// fingerprint too (the log is then rewritten once with `config` on every line, the
    /// original kept beside it as `cells.jsonl.<earlier fingerprint>`); a log
    /// written for another config is an error naming the file, and a last line cut short by
    /// an interruption is dropped.
    pub fn open(out: &Path, config: String, earlier: &[String], resume: bool) -> Result<Self> {
        let path = out.join(CELL_LOG);
        let mut done = HashMap::new();
        // The earlier fingerprint met and how many lines carry it, and the log with those
        // lines carrying `config`.
        let mut migrated: Option<(String, usize)> = None;
        let mut rewritten = String::new();
        if resume && path.exists() {
            let text = std::fs::read_to_string(&path)
                .with_context(|| format!("reading {}", path.display()))?;
            let (entries, cut) = parse_log(&text, &path)?;
            let mut kept = String::new();
            for (entry, line) in entries {
                if earlier.contains(&entry.config) {
                    migrated.get_or_insert_with(|| (entry.config.clone(), 0)).1 += 1;
                    let line = serde_json::to_string(&Entry {
                        config: config.clone(),
                        ..entry.clone()
                    })?;
                    rewritten.push_str(&line);
                    rewritten.push('\n');
                } else if entry.config != config {
                    bail!(
                        "--resume: {} holds cells of another config (fingerprint {}, this one \
                         {config}); resume with the config it was evaluated with (a log \
                         written before the fingerprint left out the checkpoint directory \
                         also needs the same --checkpoint), or evaluate into a new directory",
                        path.display(),
                        entry.config
                    );
                } else {
                    rewritten.push_str(line);
                    rewritten.push('\n');
                }
                kept.push_str(line);
                kept.push('\n');
                done.insert(entry.key, (entry.successes, entry.overruns));
            }
            if cut {
                log_line(&format!(
                    "{}: dropped a last line cut short by an interruption",
                    path.display()
                ));
                write_atomically(&path, kept.as_bytes())?;
            }
            log_line(&format!(
                "{}: {} cells measured earlier are reused",
                path.display(),
                done.len(),
            ));
            if let Some((old, count)) = &migrated {
                migrate(&path, old, &kept, &rewritten, *count)?;
            }
        } else if path.exists() {
            bail!(
                "{} exists: continue that evaluation with --resume, or choose another --out",
                path.display()
            );
        }
        Ok(Self {
            path,
            config,
            done: Mutex::new(done),
            stop: None,
        })
    }

    /// Once `flag` is set (by SIGINT or SIGTERM, `crate::signals::stop_flag`), an
    /// evaluation through this log ends with an error before it measures another cell: the
    /// cells already measured are in the log, so resuming measures only the rest. A cell
    /// being measured is finished first, and logged cells are still reused.
    pub fn stop_on(mut self, flag: Arc<AtomicBool>) -> Self {
        self.stop = Some(flag);
        self
    }

    /// Whether the stop flag is set.
    fn stopped(&self) -> bool {
        self.stop.as_ref().is_some_and(|f| f.load(Ordering::SeqCst))
    }

    /// Cells in the log.
    pub fn len(&self) -> usize {
        self.done.lock().unwrap_or_else(|e| e.into_inner()).len()
    }

    /// Whether the log holds no cell.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn get(&self, key: &CellKey) -> Option<(usize, u64)> {
        self.done
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(key)
            .copied()
    }

    /// Append one measured cell and sync it to disk before the evaluation goes on.
    fn record(&self, key: CellKey, successes: usize, overruns: u64) -> Result<()> {
        let mut done = self.done.lock().unwrap_or_else(|e| e.into_inner());
        let entry = Entry {
            config: self.config.clone(),
            key,
            successes,
            overruns,
        };
        let mut line = serde_json::to_string(&entry)?;
        line.push('\n');
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.path)
            .with_context(|| format!("opening {}", self.path.display()))?;
        f.write_all(line.as_bytes())
            .and_then(|()| f.sync_data())
            .with_context(|| format!("writing {}", self.path.display()))?;
        done.insert(entry.key, (successes, overruns));
        Ok(())
    }
}

/// Rewrite the cell log at `path` (whose text is `before`) as `after`, the same cells with
/// `count` of them moved from the earlier fingerprint `old` to this config's, once: the log
/// as it was is kept beside it as `cells.jsonl.<old>` (never overwritten), and the new text
/// replaces the log in one rename. From then on the log can be resumed from any checkpoint
/// directory.
fn migrate(path: &Path, old: &str, before: &str, after: &str, count: usize) -> Result<()> {
    let keep = path.with_file_name(format!("{CELL_LOG}.{old}"));
    if keep.exists() {
        bail!(
            "{} holds cells under the earlier fingerprint {old}, but {} exists already: \
             move it away and resume again",
            path.display(),
            keep.display()
        );
    }
    // The copy is on disk before the log is replaced, so a crash leaves either the old log
    // or the new one, and the copy.
    write_atomically(&keep, before.as_bytes())?;
    write_atomically(path, after.as_bytes())?;
    log_line(&format!(
        "{}: {count} cells were logged under this config's earlier fingerprint {old} (which \
         also hashed the checkpoint directory) and now carry its fingerprint; the log as it \
         was is kept as {}",
        path.display(),
        keep.display()
    ));
    Ok(())
}

/// The cell log of an evaluation and the checkpoint each policy × seed runs (its key).
pub struct Logged<'a> {
    /// Where measured cells are kept and looked up (and whose stop flag is polled before
    /// each cell, [`CellLog::stop_on`]).
    pub log: &'a CellLog,
    /// The checkpoint `(policy, seed)` runs, e.g. [`chosen_checkpoint`].
    pub checkpoint: &'a dyn Fn(Policy, u64) -> String,
}

impl std::fmt::Debug for Logged<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Logged")
            .field("log", &self.log)
            .finish_non_exhaustive()
    }
}

/// Name of the chosen checkpoint of the training run in `run_dir`
/// (`<policy>-seed<s>/best@<step>`, the step from `best.json`; `…/best` without it).
pub fn chosen_checkpoint(run_dir: &Path) -> String {
    let name = run_dir
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let step = std::fs::read_to_string(run_dir.join("best.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v.get("step").and_then(serde_json::Value::as_u64));
    let tag = weights_tag(&run_dir.join("best"));
    match step {
        Some(s) => format!("{name}/best@{s}{tag}"),
        None => format!("{name}/best{tag}"),
    }
}

/// Name of a step checkpoint directory `run_dir/step-NNNNNN` (`<policy>-seed<s>/step-NNNNNN`).
fn step_checkpoint(dir: &Path) -> String {
    let part = |p: Option<&Path>| {
        p.and_then(Path::file_name)
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    format!(
        "{}/{}{}",
        part(dir.parent()),
        part(Some(dir)),
        weights_tag(dir)
    )
}

/// Evaluate every row × seed × column of `study` (in that order) over the settings'
/// episodes; `models(policy, seed)` supplies what runs the action head. With `logged`, a
/// cell already in the log is taken from it, and every cell measured is appended to it.
pub fn evaluate<'m, T: Task>(
    task: &T,
    study: &Study,
    models: &dyn Fn(Policy, u64) -> &'m Models<'m>,
    logged: Option<&Logged<'_>>,
    pb: &ProgressBar,
) -> Result<Vec<Cell>> {
    let s = task.settings();
    let zero = LockstepTiming::zero_latency();
    let path = EvalPath::of(&s);
    let mut cells = Vec::new();
    for r in &study.rows {
        let (label, policy) = (&r.row.label, r.row.policy);
        for &seed in &s.seeds {
            let m = models(policy, seed);
            let checkpoint = logged.map(|l| (l.checkpoint)(policy, seed));
            // One cell: from the log when it holds it, else measured (and logged).
            let run = |column: Option<usize>, mode: &Mode, timing, what: String| {
                let key = checkpoint.as_ref().map(|c| CellKey {
                    checkpoint: c.clone(),
                    label: label.clone(),
                    column,
                    seed,
                    episodes: s.episodes,
                    eval: path.cell_tag(),
                });
                if let (Some(l), Some(k)) = (logged, &key) {
                    if let Some(res) = l.log.get(k) {
                        pb.inc(s.episodes as u64);
                        log_line(&format!("{what}: {}/{} (logged)", res.0, s.episodes));
                        return Ok(res);
                    }
                    if l.log.stopped() {
                        bail!(
                            "evaluation stopped by a signal before {what}: the {} cells \
                             measured are kept in {}, and resuming in the same directory with \
                             the same config measures only the rest",
                            l.log.len(),
                            l.log.path.display()
                        );
                    }
                }
                let res = closed_loop(
                    task,
                    m,
                    policy,
                    mode,
                    timing,
                    s.episodes,
                    study.seed_base + seed,
                    path,
                    &|| pb.inc(1),
                )?;
                if let (Some(l), Some(k)) = (logged, key) {
                    l.log.record(k, res.0, res.1)?;
                }
                log_line(&format!("{what}: {}/{}", res.0, s.episodes));
                Ok::<_, anyhow::Error>(res)
            };
            let once = match r.sweep {
                Sweep::Once(timing) => Some(run(
                    None,
                    &r.row.mode,
                    timing,
                    format!("{label} seed {seed}"),
                )?),
                _ => None,
            };
            for &col in &study.columns {
                let (successes, overruns) = match (r.sweep, once) {
                    (_, Some(res)) => res,
                    (Sweep::Horizon, None) => {
                        let Mode::SyncFlow { steps, .. } = r.row.mode else {
                            bail!("row {label}: a horizon sweep needs a sync-flow mode");
                        };
                        run(
                            Some(col),
                            &Mode::SyncFlow { steps, h: col },
                            zero,
                            format!("{label} h={col} seed {seed}"),
                        )?
                    }
                    (Sweep::UnitDelaySync, None) => {
                        let Mode::SyncFlow { steps, .. } = r.row.mode else {
                            bail!("row {label}: a sync unit-delay sweep needs a sync-flow mode");
                        };
                        let timing = LockstepTiming::for_mode(&r.row.mode, col);
                        let h = timing.call_ticks.max(1);
                        run(
                            Some(col),
                            &Mode::SyncFlow { steps, h },
                            timing,
                            format!("{label} d0={col} (h={h}) seed {seed}"),
                        )?
                    }
                    _ => {
                        let mode = &r.row.mode;
                        run(
                            Some(col),
                            mode,
                            LockstepTiming::for_mode(mode, col),
                            format!("{label} d0={col} seed {seed}"),
                        )?
                    }
                };
                cells.push(Cell {
                    label: label.clone(),
                    d0: col,
                    seed,
                    successes,
                    episodes: s.episodes,
                    overruns,
                });
            }
        }
    }
    Ok(cells)
}

/// The last `k` step checkpoints (`step-NNNNNN/`, latest first) of the training run in `dir`
/// among `steps` (the steps a run writes them at, [`task_checkpoint_steps`]), leaving out the
/// chosen one (the step named by `dir/best.json`), whose cells are measured anyway. Fewer when
/// the run writes fewer. A run that lacks any of them (one restored from the state that
/// travels between machines has only `best/`) is an error naming the missing steps: its
/// best-per-cell cells would otherwise quietly be its chosen checkpoint's, a table
/// `pir2 report` refuses for the same log.
pub fn last_step_checkpoints(dir: &Path, steps: &[usize], k: usize) -> Result<Vec<PathBuf>> {
    let chosen = std::fs::read_to_string(dir.join("best.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v.get("step").and_then(serde_json::Value::as_u64));
    let wanted: Vec<String> = steps
        .iter()
        .rev()
        .filter(|&&s| Some(s as u64) != chosen)
        .take(k)
        .map(|s| format!("step-{s:06}"))
        .collect();
    let missing: Vec<&str> = wanted
        .iter()
        .filter(|name| !dir.join(name).is_dir())
        .map(String::as_str)
        .collect();
    if !missing.is_empty() {
        bail!(
            "{}: the best-checkpoint-per-cell protocol (best_of_last = {k}) takes its step \
             checkpoint(s) {} and the run does not have them (a run's step checkpoints do not \
             travel with its saved state); measure its best-per-cell cells where it was \
             trained, or evaluate with --best-of-last 0 for the chosen checkpoint's cells",
            dir.display(),
            missing.join(", ")
        );
    }
    Ok(wanted.iter().map(|name| dir.join(name)).collect())
}

/// The paper's optimistic checkpoint protocol ("for each cell we pick the best epoch per
/// seed"): every cell of `study` is evaluated again with each of the last `k` step
/// checkpoints of its training run ([`last_step_checkpoints`]), and per row × column × seed
/// the best success count of those and of `chosen` (the cells of the chosen checkpoints) is
/// kept. It selects on the evaluation episodes themselves, so it is optimistic; the study
/// reports it next to, never instead of, the chosen-checkpoint cells. With `log`, cells are
/// reused from and kept in the cell log as in [`evaluate`], and the log's stop flag ends the
/// evaluation before the next cell ([`CellLog::stop_on`]).
pub fn evaluate_best_per_cell<T: Task>(
    task: &T,
    study: &Study,
    trained: &[Trained],
    k: usize,
    chosen: &[Cell],
    log: Option<&CellLog>,
    pb: &ProgressBar,
) -> Result<Vec<Cell>> {
    let mut best = chosen.to_vec();
    let steps = task_checkpoint_steps(task);
    let ckpts = trained
        .iter()
        .map(|t| last_step_checkpoints(&t.dir, &steps, k))
        .collect::<Result<Vec<_>>>()?;
    for j in 0..k {
        // The j-th latest other checkpoint of every run that has one; the rest keep their
        // chosen model, and rows none of whose runs have a j-th checkpoint are skipped.
        let models = trained
            .iter()
            .zip(&ckpts)
            .map(|(t, c)| match c.get(j) {
                Some(dir) => {
                    let m = CandleModel::load_expect(dir, &task.spec())
                        .with_context(|| format!("loading {}", dir.display()))?;
                    crate::identity::expect_policy(&m, dir, t.policy, "evaluating it as")?;
                    Ok((
                        t.policy,
                        t.seed,
                        Models::local(&m)?,
                        Some(step_checkpoint(dir)),
                    ))
                }
                None => Ok((t.policy, t.seed, Models::local(&t.model)?, None)),
            })
            .collect::<Result<Vec<_>>>()?;
        let rows: Vec<_> = study
            .rows
            .iter()
            .filter(|r| models.iter().any(|m| m.0 == r.row.policy && m.3.is_some()))
            .cloned()
            .collect();
        if rows.is_empty() {
            break;
        }
        let sub = Study {
            rows,
            ..study.clone()
        };
        let find = |p: Policy, s: u64| {
            models
                .iter()
                .find(|m| m.0 == p && m.1 == s)
                .expect("every policy of the study was trained")
        };
        let checkpoint = |p: Policy, s: u64| match &find(p, s).3 {
            Some(c) => c.clone(),
            None => chosen_checkpoint(&trained_dir(trained, p, s)),
        };
        let logged = log.map(|log| Logged {
            log,
            checkpoint: &checkpoint,
        });
        let cells = evaluate(task, &sub, &|p, s| &find(p, s).2, logged.as_ref(), pb)?;
        for c in cells {
            if let Some(b) = best
                .iter_mut()
                .find(|b| b.label == c.label && b.d0 == c.d0 && b.seed == c.seed)
            {
                if c.successes > b.successes {
                    *b = c;
                }
            }
        }
    }
    Ok(best)
}

/// The training-run directory of `(policy, seed)` among `trained`.
pub fn trained_dir(trained: &[Trained], policy: Policy, seed: u64) -> PathBuf {
    trained
        .iter()
        .find(|t| t.policy == policy && t.seed == seed)
        .map(|t| t.dir.clone())
        .unwrap_or_default()
}

/// Episodes `study` runs in total (for a progress bar).
pub fn total_episodes<T: Task>(task: &T, study: &Study) -> usize {
    let s = task.settings();
    let per_seed: usize = study
        .rows
        .iter()
        .map(|r| match r.sweep {
            Sweep::Once(_) => 1,
            _ => study.columns.len(),
        })
        .sum();
    per_seed * s.seeds.len() * s.episodes
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("pir2-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// A set stop flag (SIGINT / SIGTERM) ends the evaluation before the first cell it would
    /// measure, with one error naming the log; cells already in the log are still reused,
    /// nothing is measured or logged after the flag, and a resumed run measures the rest.
    #[test]
    fn a_set_stop_flag_ends_the_evaluation_before_the_next_unlogged_cell() {
        use super::super::ballplate::{BallPlateTask, DemoConfig};
        use pir2_backends::{Config, Stats};

        let task = BallPlateTask::new(DemoConfig {
            episodes: 2,
            seeds: vec![0],
            d0s: vec![1, 2],
            width: 16,
            depth: 1,
            ..DemoConfig::default()
        });
        let spec = task.spec();
        let model = CandleModel::new(
            Config {
                spec,
                model: task.model(Policy::PiR2),
            },
            Stats::identity(&spec),
            0,
        )
        .unwrap();
        let models = Models::local(&model).unwrap();
        let row = task
            .rows()
            .into_iter()
            .find(|r| r.policy == Policy::PiR2)
            .unwrap();
        let label = row.label.clone();
        let study = Study::deployment(vec![row], &[1, 2]);
        let dir = tmp("cell-log-stop");
        let stop = Arc::new(AtomicBool::new(true));
        let log = CellLog::open(&dir, "aaaa".into(), &[], false)
            .unwrap()
            .stop_on(stop.clone());
        // The first cell is in the log already, with counts no measurement of 2 episodes
        // could give (so reuse shows).
        let first = CellKey {
            checkpoint: "ckpt".into(),
            label: label.clone(),
            column: Some(1),
            seed: 0,
            episodes: 2,
            eval: None,
        };
        log.record(first, 2, 77).unwrap();
        let checkpoint = |_: Policy, _: u64| "ckpt".to_string();
        let logged = Logged {
            log: &log,
            checkpoint: &checkpoint,
        };
        let pb = ProgressBar::hidden();
        let err = evaluate(&task, &study, &|_, _| &models, Some(&logged), &pb)
            .unwrap_err()
            .to_string();
        assert!(err.contains("stopped by a signal"), "{err}");
        assert!(err.contains(&format!("{label} d0=2 seed 0")), "{err}");
        assert!(err.contains(&log.path.display().to_string()), "{err}");
        assert_eq!(log.len(), 1, "nothing measured after the stop");
        assert_eq!(pb.position(), 2, "the logged cell was reused");
        // Resumed (the flag clear): the logged cell is reused, the other measured.
        stop.store(false, Ordering::SeqCst);
        let cells = evaluate(&task, &study, &|_, _| &models, Some(&logged), &pb).unwrap();
        assert_eq!(cells.len(), 2);
        assert_eq!((cells[0].d0, cells[0].overruns), (1, 77));
        assert_eq!(cells[1].d0, 2);
        assert_eq!(log.len(), 2);
    }

    #[test]
    fn last_step_checkpoints_are_latest_first_without_the_chosen_one() {
        let dir = tmp("last-steps");
        for step in [100, 200, 300, 400] {
            std::fs::create_dir_all(dir.join(format!("step-{step:06}"))).unwrap();
        }
        std::fs::create_dir_all(dir.join("best")).unwrap();
        std::fs::write(dir.join("step-000500"), "a file, not a checkpoint").unwrap();
        let steps = [100, 200, 300, 400];
        let names = |k| -> Vec<String> {
            last_step_checkpoints(&dir, &steps, k)
                .unwrap()
                .iter()
                .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
                .collect()
        };
        assert_eq!(names(2), ["step-000400", "step-000300"]);
        assert_eq!(
            chosen_checkpoint(&dir),
            format!("{}/best", dir.file_name().unwrap().to_string_lossy())
        );
        std::fs::write(dir.join("best.json"), r#"{"step": 400, "score": 0.5}"#).unwrap();
        assert_eq!(names(2), ["step-000300", "step-000200"]);
        assert_eq!(names(9), ["step-000300", "step-000200", "step-000100"]);
        assert!(names(0).is_empty());
        assert!(chosen_checkpoint(&dir).ends_with("/best@400"));
        // A run without some of the steps the protocol takes (restored from its travelling
        // state) is refused by name, never evaluated as if its chosen checkpoint were them.
        std::fs::remove_dir(dir.join("step-000200")).unwrap();
        assert_eq!(names(1), ["step-000300"]);
        let e = last_step_checkpoints(&dir, &steps, 2)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("step-000200") && !e.contains("step-000300"),
            "{e}"
        );
        assert!(e.contains("best_of_last = 2"), "{e}");
        // With weights, the key names them: other weights under the same name and step
        // (a retrained run) make another key, the same weights the same key.
        std::fs::write(dir.join("best/model.safetensors"), b"weights a").unwrap();
        let a = chosen_checkpoint(&dir);
        assert!(a.contains("/best@400#w"), "{a}");
        std::fs::write(dir.join("best/model.safetensors"), b"weights b").unwrap();
        let b = chosen_checkpoint(&dir);
        assert_ne!(a, b);
        std::fs::write(dir.join("best/model.safetensors"), b"weights a").unwrap();
        assert_eq!(chosen_checkpoint(&dir), a);
        let step = dir.join("step-000300");
        assert!(step_checkpoint(&step).ends_with("/step-000300"));
        std::fs::write(step.join("model.safetensors"), b"weights a").unwrap();
        assert_eq!(
            step_checkpoint(&step).split_once('#').map(|(_, t)| t),
            a.split_once('#').map(|(_, t)| t)
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    fn key(label: &str, column: Option<usize>, seed: u64) -> CellKey {
        CellKey {
            checkpoint: "flow-seed0/best@100".into(),
            label: label.into(),
            column,
            seed,
            episodes: 20,
            eval: None,
        }
    }

    #[test]
    fn the_cell_log_keeps_cells_across_runs_of_the_same_config_only() {
        let dir = tmp("cell-log");
        let log = CellLog::open(&dir, "aaaa".into(), &[], false).unwrap();
        assert!(log.is_empty());
        log.record(key("sync flow", Some(1), 0), 7, 2).unwrap();
        log.record(key("πR² async", None, 0), 9, 0).unwrap();
        drop(log);
        // Without --resume an existing log is refused by name; nothing is changed.
        let before = std::fs::read_to_string(dir.join(CELL_LOG)).unwrap();
        let e = CellLog::open(&dir, "aaaa".into(), &[], false).unwrap_err();
        assert!(e.to_string().contains("--resume"), "{e}");
        // Resumed with the same config: both cells, keyed exactly.
        let log = CellLog::open(&dir, "aaaa".into(), &[], true).unwrap();
        assert_eq!(log.len(), 2);
        assert_eq!(log.get(&key("sync flow", Some(1), 0)), Some((7, 2)));
        assert_eq!(log.get(&key("sync flow", Some(2), 0)), None);
        assert_eq!(log.get(&key("sync flow", Some(1), 1)), None);
        assert_eq!(log.get(&key("πR² async", None, 0)), Some((9, 0)));
        let mut other_ckpt = key("sync flow", Some(1), 0);
        other_ckpt.checkpoint = "flow-seed0/step-000200".into();
        assert_eq!(log.get(&other_ckpt), None);
        drop(log);
        // Another config: one error naming the file; the log is untouched.
        let e = CellLog::open(&dir, "bbbb".into(), &[], true).unwrap_err();
        assert!(e.to_string().contains(CELL_LOG), "{e}");
        assert_eq!(std::fs::read_to_string(dir.join(CELL_LOG)).unwrap(), before);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn batched_cells_are_keyed_apart_and_logs_without_the_tag_keep_their_keys() {
        // A batch-1 cell's line carries no `eval` field (as in logs written before batched
        // evaluation existed) and reads back as a batch-1 key.
        let line = serde_json::to_string(&Entry {
            config: "aaaa".into(),
            key: key("sync flow", Some(1), 0),
            successes: 7,
            overruns: 0,
        })
        .unwrap();
        assert!(!line.contains("eval"), "{line}");
        let old = r#"{"config":"aaaa","checkpoint":"flow-seed0/best@100","label":"sync flow","column":1,"seed":0,"episodes":20,"successes":7,"overruns":0}"#;
        let e: Entry = serde_json::from_str(old).unwrap();
        assert_eq!(e.key, key("sync flow", Some(1), 0));
        // A batched cell of the same checkpoint, row and column is another cell.
        let dir = tmp("cell-log-batched");
        let log = CellLog::open(&dir, "aaaa".into(), &[], false).unwrap();
        log.record(key("sync flow", Some(1), 0), 7, 0).unwrap();
        let mut batched = key("sync flow", Some(1), 0);
        batched.eval = EvalPath::Batched(32).cell_tag();
        assert!(batched
            .eval
            .as_deref()
            .unwrap()
            .starts_with("batched g32 k"));
        assert_eq!(EvalPath::Threads(2).cell_tag(), None);
        assert_eq!(log.get(&batched), None);
        log.record(batched.clone(), 9, 0).unwrap();
        drop(log);
        let log = CellLog::open(&dir, "aaaa".into(), &[], true).unwrap();
        assert_eq!(log.get(&key("sync flow", Some(1), 0)), Some((7, 0)));
        assert_eq!(log.get(&batched), Some((9, 0)));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_last_line_cut_short_is_dropped_and_a_bad_line_elsewhere_is_an_error() {
        let dir = tmp("cell-log-cut");
        let log = CellLog::open(&dir, "aaaa".into(), &[], false).unwrap();
        log.record(key("sync flow", Some(1), 0), 7, 0).unwrap();
        drop(log);
        let path = dir.join(CELL_LOG);
        let whole = std::fs::read_to_string(&path).unwrap();
        std::fs::write(&path, format!("{whole}{}", &whole[..whole.len() / 2])).unwrap();
        let log = CellLog::open(&dir, "aaaa".into(), &[], true).unwrap();
        assert_eq!(log.len(), 1);
        assert_eq!(std::fs::read_to_string(&path).unwrap(), whole);
        // Appending after the repair keeps one cell per line.
        log.record(key("sync flow", Some(2), 0), 3, 0).unwrap();
        drop(log);
        assert_eq!(
            CellLog::open(&dir, "aaaa".into(), &[], true).unwrap().len(),
            2
        );
        std::fs::write(&path, format!("not json\n{whole}")).unwrap();
        let e = CellLog::open(&dir, "aaaa".into(), &[], true).unwrap_err();
        assert!(e.to_string().contains("line 1"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn cells_logged_under_an_earlier_fingerprint_are_migrated_once_and_the_old_log_kept() {
        let dir = tmp("cell-log-earlier");
        let log = CellLog::open(&dir, "old0".into(), &[], false).unwrap();
        log.record(key("sync flow", Some(1), 0), 7, 2).unwrap();
        log.record(key("sync flow", Some(2), 0), 5, 0).unwrap();
        drop(log);
        let path = dir.join(CELL_LOG);
        let before = std::fs::read_to_string(&path).unwrap();
        // Without the earlier fingerprint the log is another config's; nothing changes.
        let e = CellLog::open(&dir, "new0".into(), &[], true).unwrap_err();
        assert!(e.to_string().contains("--checkpoint"), "{e}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), before);
        // With it, the cells are reused, the log now carries the new fingerprint on every
        // line, and the log as it was is kept beside it.
        let earlier = ["old0".to_string()];
        let log = CellLog::open(&dir, "new0".into(), &earlier, true).unwrap();
        assert_eq!(log.get(&key("sync flow", Some(1), 0)), Some((7, 2)));
        assert_eq!(log.get(&key("sync flow", Some(2), 0)), Some((5, 0)));
        assert_eq!(
            std::fs::read_to_string(dir.join("cells.jsonl.old0")).unwrap(),
            before
        );
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            before.replace(r#""config":"old0""#, r#""config":"new0""#)
        );
        log.record(key("sync flow", Some(3), 0), 3, 0).unwrap();
        drop(log);
        // Migrated: it opens without the earlier fingerprint (from any checkpoint directory).
        let log = CellLog::open(&dir, "new0".into(), &[], true).unwrap();
        assert_eq!(log.len(), 3);
        drop(log);
        // A kept log is never overwritten: a second migration into it is refused by name.
        std::fs::write(&path, &before).unwrap();
        let e = CellLog::open(&dir, "new0".into(), &earlier, true).unwrap_err();
        assert!(e.to_string().contains("cells.jsonl.old0"), "{e}");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), before);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_checkpoint_directory_left_the_fingerprint_and_its_earlier_value_is_kept() {
        #[derive(Serialize)]
        struct C {
            episodes: usize,
            pretrained: Option<String>,
            train_missing: bool,
        }
        let at = |p: Option<&str>, train_missing| C {
            episodes: 100,
            pretrained: p.map(Into::into),
            train_missing,
        };
        let f = |c: &C| config_fingerprint(c).unwrap();
        let before = |c: &C| earlier_config_fingerprints(c).unwrap();
        // Where the checkpoints lie, and whether missing ones may be trained, change nothing.
        assert_eq!(f(&at(Some("runs/a"), false)), f(&at(Some("runs/b"), true)));
        assert_eq!(f(&at(Some("runs/a"), false)), f(&at(None, false)));
        // The earlier fingerprint hashed the path (and knew no `train_missing`): one per path.
        #[derive(Serialize)]
        struct Old {
            episodes: usize,
            pretrained: Option<String>,
        }
        let old = config_fingerprint(&Old {
            episodes: 100,
            pretrained: None,
        })
        .unwrap();
        assert_eq!(before(&at(None, true)), Vec::<String>::new());
        assert_eq!(f(&at(None, true)), old);
        let a = before(&at(Some("runs/a"), true));
        assert_eq!(a.len(), 1);
        assert_ne!(a, before(&at(Some("runs/b"), false)));
        assert_eq!(a, before(&at(Some("runs/a"), false)));
        assert_ne!(a[0], f(&at(Some("runs/a"), false)));
    }

    #[test]
    fn the_fingerprint_ignores_what_is_evaluated_not_how() {
        #[derive(Serialize)]
        struct C {
            episodes: usize,
            max_steps: usize,
            policies: Vec<&'static str>,
            seeds: Vec<u64>,
            d0s: Vec<usize>,
            best_of_last: usize,
            threads: usize,
            batch_episodes: usize,
        }
        let base = C {
            episodes: 100,
            max_steps: 600,
            policies: vec!["flow"],
            seeds: vec![0],
            d0s: vec![1],
            best_of_last: 0,
            threads: 1,
            batch_episodes: 1,
        };
        let f = |c: &C| config_fingerprint(c).unwrap();
        assert_eq!(f(&base).len(), 16);
        let wider = C {
            policies: vec!["flow", "rtc"],
            seeds: vec![0, 1, 2],
            d0s: vec![1, 2, 3],
            best_of_last: 3,
            threads: 2,
            batch_episodes: 32,
            ..base
        };
        assert_eq!(f(&wider), f(&base));
        assert_ne!(
            f(&C {
                max_steps: 300,
                ..wider
            }),
            f(&base)
        );
    }
}
