//! A study's tables from its cell log alone (`pir2 report`).
//!
//! One file on purpose: which cells a report takes must be exactly those `pir2 eval` takes
//! (the trainer's steps, the chosen checkpoint, the log's key); the tests of that are almost
//! half the file.
//!
//! `pir2 eval` keeps every cell it measures in `cells.jsonl`, keyed by what the cell depends
//! on: the checkpoint that ran (training run, step and the weights' hash), the row, the
//! column, the seed, the episode count and the evaluation path, under the fingerprint of the
//! config ([`super::evaluate`]). Those keys are enough to rebuild what the evaluation reports,
//! the chosen-checkpoint table and the best checkpoint per cell, without the checkpoints and
//! without the simulator. A study whose runs are gone (a lost machine), or whose cells were
//! measured over several sittings with several narrowed configs, is reported from its log
//! by one command, with the numbers `pir2 eval` gives over the same checkpoints.
//!
//! Which checkpoints a cell takes, per training run `<policy>-seed<s>`:
//! - the chosen one is the log's `<run>/best@<step>`; cells of two different sets of weights
//!   under that name (runs trained apart, on CPUs that round differently) are an error naming
//!   both;
//! - the best-per-cell protocol ([`super::evaluate::evaluate_best_per_cell`]) adds the last
//!   `best_of_last` other step checkpoints the run writes. These are the steps at every
//!   `steps / checkpoints` steps and at the end, from the config, exactly those
//!   [`super::evaluate::last_step_checkpoints`] finds in a finished run. A step the log holds
//!   but the protocol does not take (a diagnostic look at an early checkpoint) is left out.
//!
//! A cell the log lacks is an error listing what is missing, unless a partial report is asked
//! for: then a missing chosen cell is left out of the tables, a best-per-cell cell is given
//! only when all of its checkpoints are in the log, and the report lists what is missing.
//! The log is only read.

use std::collections::{BTreeSet, HashMap};
use std::path::Path;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use super::evaluate::{config_fingerprint, earlier_config_fingerprints, parse_log, Entry};
use super::pipeline::{
    checkpoint_every, log_line, plot_study, policy_dir, prepare_out, write_atomically, EvalPath,
};
use super::{cells, Cell, Study, Sweep, Task};

/// The logged cells of a study by checkpoint, row label, column and seed: successes and
/// overruns.
type CellIndex<'a> = HashMap<(&'a str, &'a str, Option<usize>, u64), (usize, u64)>;

/// Missing cells named in the error of a report that is not partial.
const NAMED_MISSING: usize = 12;

/// The checkpoints of one training run a report takes its cells from (cell-log names,
/// `<run>/best@<step>#w<hash>`, `<run>/step-NNNNNN#w<hash>`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RunCheckpoints {
    /// The run, `<policy>-seed<s>`.
    pub run: String,
    /// The chosen checkpoint, when the log holds cells of it.
    pub chosen: Option<String>,
    /// The step checkpoints of the best-per-cell protocol, latest first: the step, and its
    /// name when the log holds cells of it.
    pub others: Vec<(usize, Option<String>)>,
}

/// A study reported from a cell log ([`report`]).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LogReport<C> {
    /// Study name (`deployment`, `horizon`).
    pub study: String,
    /// The config the report was asked for.
    pub config: C,
    /// Its fingerprint, the one its cells are logged under.
    pub fingerprint: String,
    /// Row labels in table order.
    pub labels: Vec<String>,
    /// Column key (`d0`, `h`).
    pub key: String,
    /// Column values.
    pub columns: Vec<usize>,
    /// Seeds.
    pub seeds: Vec<u64>,
    /// Evaluation episodes per cell and seed.
    pub episodes: usize,
    /// The cells of the chosen checkpoints (`d0` holds the column value).
    pub cells: Vec<Cell>,
    /// Step checkpoints besides the chosen one each best-per-cell cell considers (0: none).
    pub best_of_last: usize,
    /// The best checkpoint per row × column × seed (empty when `best_of_last` is 0).
    pub best_per_cell: Vec<Cell>,
    /// The checkpoints each training run's cells come from.
    pub runs: Vec<RunCheckpoints>,
    /// Cells of this study the log lacks (empty unless the report is partial).
    pub missing: Vec<String>,
    /// Lines of the log that are not of this study's config, episode count and evaluation
    /// path (other studies' cells kept in the same log).
    pub other_lines: usize,
}

impl<C> LogReport<C> {
    /// The Markdown tables: the chosen checkpoints (mean ± std over seeds, then per seed),
    /// the best checkpoint per cell the same way, and what is missing.
    pub fn table(&self) -> String {
        let seeds: Vec<String> = self.seeds.iter().map(u64::to_string).collect();
        // The binomial standard error of a cell's mean over the seeds' episodes, at its
        // largest (p = 1/2): the sampling error a difference of two cells carries √2 times.
        let n = (self.seeds.len() * self.episodes).max(1) as f64;
        let mut t = format!(
            "Chosen checkpoints (the primary protocol), mean ± population std (÷ n) over seeds \
             {}; a cell mean's binomial standard error is at most {:.3} ({} episodes):\n\n",
            seeds.join(", "),
            (0.25 / n).sqrt(),
            n
        );
        t += &cells::table_keyed(&self.cells, &self.labels, &self.columns, &self.key);
        t += "\nPer seed:\n\n";
        t += &cells::per_seed_table(
            &self.cells,
            &self.labels,
            &self.columns,
            &self.key,
            &self.seeds,
        );
        if self.best_of_last > 0 {
            t += &format!(
                "\nBest checkpoint per cell (the paper's protocol; optimistic: per seed, the best \
                 of the chosen checkpoint and the last {} other step checkpoints, selected on \
                 the evaluation episodes: a maximum of {} candidates on the test episodes, biased \
                 upward), mean ± population std over seeds:\n\n",
                self.best_of_last,
                self.best_of_last + 1
            );
            t += &cells::table_keyed(&self.best_per_cell, &self.labels, &self.columns, &self.key);
            t += "\nPer seed:\n\n";
            t += &cells::per_seed_table(
                &self.best_per_cell,
                &self.labels,
                &self.columns,
                &self.key,
                &self.seeds,
            );
        }
        if !self.missing.is_empty() {
            t += &format!(
                "\nPartial: {} cells are not in the log and are left out (a mean is over the \
                 seeds that have the cell):\n\n",
                self.missing.len()
            );
            for m in &self.missing {
                t += &format!("- {m}\n");
            }
        }
        t
    }
}

/// The steps at which a run of `steps` training steps writes its `checkpoints` step
/// checkpoints (every `steps / checkpoints` steps and at the end, as the pipeline trains).
pub fn checkpoint_steps(steps: usize, checkpoints: usize) -> Vec<usize> {
    let every = checkpoint_every(steps, checkpoints);
    (1..=steps)
        .filter(|s| s % every == 0 || *s == steps)
        .collect()
}

/// The step checkpoints a training run of `task` writes ([`checkpoint_steps`] of its
/// optimiser's steps and its settings' `checkpoints`).
pub fn task_checkpoint_steps<T: Task>(task: &T) -> Vec<usize> {
    checkpoint_steps(task.optimiser().steps, task.settings().checkpoints)
}

/// Whether the cell-log checkpoint name `name` is `base` (with a `@<step>` or `#w<hash>`
/// suffix, or none).
fn is_named(name: &str, base: &str) -> bool {
    name.strip_prefix(base)
        .is_some_and(|rest| rest.is_empty() || rest.starts_with('@') || rest.starts_with('#'))
}

/// The one checkpoint among `found` (distinct cell-log names of `what`), none, or an error
/// naming them all when the log holds more than one set of weights under that name.
fn at_most_one(found: BTreeSet<&str>, what: &str, log: &Path) -> Result<Option<String>> {
    if found.len() > 1 {
        bail!(
            "{}: {what} has cells of {} different checkpoints ({}): runs trained apart wrote \
             other weights under the same name; report from a log of one of them",
            log.display(),
            found.len(),
            found.into_iter().collect::<Vec<_>>().join(", ")
        );
    }
    Ok(found.into_iter().next().map(str::to_string))
}

/// The checkpoints of `run` in the study's cells `mine`: the chosen one and, with `k > 0`,
/// the last `k` of `steps` other than the chosen step, latest first.
fn run_checkpoints(
    mine: &[&Entry],
    run: &str,
    steps: &[usize],
    k: usize,
    log: &Path,
) -> Result<RunCheckpoints> {
    let base = format!("{run}/best");
    let chosen = at_most_one(
        mine.iter()
            .map(|e| e.key.checkpoint.as_str())
            .filter(|c| is_named(c, &base))
            .collect(),
        &format!("the chosen checkpoint of {run}"),
        log,
    )?;
    let mut others = Vec::new();
    if let (Some(c), true) = (&chosen, k > 0) {
        let chosen_step = c[base.len()..]
            .strip_prefix('@')
            .and_then(|r| r.split('#').next())
            .and_then(|s| s.parse::<usize>().ok());
        for &step in steps
            .iter()
            .rev()
            .filter(|s| Some(**s) != chosen_step)
            .take(k)
        {
            let base = format!("{run}/step-{step:06}");
            let found = mine
                .iter()
                .map(|e| e.key.checkpoint.as_str())
                .filter(|c| is_named(c, &base))
                .collect();
            others.push((step, at_most_one(found, &base, log)?));
        }
    }
    Ok(RunCheckpoints {
        run: run.to_string(),
        chosen,
        others,
    })
}

/// Report `study` of `task` from the cell logs `logs` (only read; one log, or several whose
/// cells are taken together, e.g. a study's own log and the log its baselines were measured
/// in): the cells of the task's config (its fingerprint, or an earlier one of the same
/// config; for a policy, also those of the configs [`Task::equivalent_fingerprints`] names,
/// taken for that policy's runs only), episode count and evaluation path; the chosen
/// checkpoint of each run and, with the settings' `best_of_last`, the best checkpoint per
/// cell, as `pir2 eval` computes them (see the module docs). A cell the logs lack is an
/// error naming it, unless `partial`.
pub fn report<T: Task>(
    task: &T,
    study: &Study,
    logs: &[&Path],
    partial: bool,
) -> Result<LogReport<T::Config>> {
    let s = task.settings();
    let shown = logs
        .iter()
        .map(|l| l.display().to_string())
        .collect::<Vec<_>>()
        .join(" + ");
    let log = Path::new(&shown);
    let mut texts = Vec::with_capacity(logs.len());
    for l in logs {
        texts.push((
            std::fs::read_to_string(l).with_context(|| format!("reading {}", l.display()))?,
            *l,
        ));
    }
    let mut entries = Vec::new();
    for (text, l) in &texts {
        let (e, cut) = parse_log(text, l)?;
        if cut {
            log_line(&format!(
                "{}: a last line cut short by an interruption is left out",
                l.display()
            ));
        }
        entries.extend(e);
    }
    let fingerprint = config_fingerprint(task.config())?;
    let mut fingerprints = earlier_config_fingerprints(task.config())?;
    fingerprints.push(fingerprint.clone());
    // Per policy: the other fingerprints its cells count under, and its runs' names.
    let mut equivalent: Vec<(Vec<String>, Vec<String>)> = Vec::new();
    for p in study.policies() {
        let fps = task.equivalent_fingerprints(p)?;
        if !fps.is_empty() {
            let runs = s.seeds.iter().map(|&seed| policy_dir(p, seed)).collect();
            equivalent.push((fps, runs));
        }
    }
    let of_this_config = |e: &Entry| {
        fingerprints.contains(&e.config)
            || equivalent.iter().any(|(fps, runs)| {
                fps.contains(&e.config)
                    && runs.iter().any(|r| {
                        e.key
                            .checkpoint
                            .strip_prefix(r.as_str())
                            .is_some_and(|rest| rest.starts_with('/'))
                    })
            })
    };
    let tag = EvalPath::of(&s).cell_tag();
    let mine: Vec<&Entry> = entries
        .iter()
        .map(|(e, _)| e)
        .filter(|e| of_this_config(e) && e.key.episodes == s.episodes && e.key.eval == tag)
        .collect();
    if mine.is_empty() {
        let logged: BTreeSet<&str> = entries.iter().map(|(e, _)| e.config.as_str()).collect();
        bail!(
            "{} holds no cell of this config at {} episodes per cell{} (config fingerprint \
             {fingerprint}; the log's: {}): report with the config the cells were measured \
             with, and the same dataset",
            log.display(),
            s.episodes,
            tag.as_deref()
                .map_or_else(|| ", batch-1".to_string(), |t| format!(", {t}")),
            logged.into_iter().collect::<Vec<_>>().join(", ")
        );
    }
    let mut by_key: CellIndex = HashMap::new();
    for e in &mine {
        let k = &e.key;
        let res = (e.successes, e.overruns);
        let key = (k.checkpoint.as_str(), k.label.as_str(), k.column, k.seed);
        if let Some(before) = by_key.insert(key, res) {
            if before != res {
                bail!(
                    "{}: the cell {} / {} / column {:?} / seed {} is logged twice with other \
                     results ({} and {} successes)",
                    log.display(),
                    k.checkpoint,
                    k.label,
                    k.column,
                    k.seed,
                    before.0,
                    res.0
                );
            }
        }
    }
    let steps = task_checkpoint_steps(task);
    let k = s.best_of_last;
    let mut runs = Vec::new();
    for p in study.policies() {
        for &seed in &s.seeds {
            runs.push(run_checkpoints(
                &mine,
                &policy_dir(p, seed),
                &steps,
                k,
                log,
            )?);
        }
    }
    let mut cells = Vec::new();
    let mut best_per_cell = Vec::new();
    let mut missing: Vec<String> = Vec::new();
    let mut miss = |m: String| {
        if !missing.contains(&m) {
            missing.push(m);
        }
    };
    for r in &study.rows {
        let label = r.row.label.as_str();
        for &seed in &s.seeds {
            let run = policy_dir(r.row.policy, seed);
            let rc = runs
                .iter()
                .find(|c| c.run == run)
                .expect("every policy × seed of the study has its checkpoints");
            for &col in &study.columns {
                let column = match r.sweep {
                    Sweep::Once(_) => None,
                    _ => Some(col),
                };
                let what = match column {
                    Some(c) => format!("{label}, {}={c}, seed {seed}", study.key),
                    None => format!("{label}, seed {seed}"),
                };
                let get = |name: &Option<String>| {
                    name.as_deref()
                        .and_then(|n| by_key.get(&(n, label, column, seed)).copied())
                };
                let cell = |(successes, overruns): (usize, u64)| Cell {
                    label: label.to_string(),
                    d0: col,
                    seed,
                    successes,
                    episodes: s.episodes,
                    overruns,
                };
                let chosen = get(&rc.chosen);
                match chosen {
                    Some(c) => cells.push(cell(c)),
                    None => miss(format!(
                        "{what}: {}",
                        rc.chosen
                            .clone()
                            .unwrap_or_else(|| format!("no chosen checkpoint of {run}"))
                    )),
                }
                if k == 0 {
                    continue;
                }
                // As the evaluation: the chosen cell, replaced by a later-listed checkpoint's
                // only when that one has strictly more successes.
                let mut best = chosen;
                let mut complete = chosen.is_some();
                for (step, name) in &rc.others {
                    match get(name) {
                        Some(c) => {
                            if best.is_some_and(|b| c.0 > b.0) {
                                best = Some(c);
                            }
                        }
                        None => {
                            complete = false;
                            miss(format!("{what}: {run}/step-{step:06}"));
                        }
                    }
                }
                if let (Some(b), true) = (best, complete) {
                    best_per_cell.push(cell(b));
                }
            }
        }
    }
    if !missing.is_empty() && !partial {
        let named: Vec<&str> = missing
            .iter()
            .take(NAMED_MISSING)
            .map(String::as_str)
            .collect();
        bail!(
            "{} lacks {} cells of this study ({}{}): measure them with `pir2 eval … --resume`, \
             or report what the log holds with --partial",
            log.display(),
            missing.len(),
            named.join("; "),
            if missing.len() > NAMED_MISSING {
                "; …"
            } else {
                ""
            }
        );
    }
    Ok(LogReport {
        study: study.name.clone(),
        config: task.config().clone(),
        fingerprint,
        labels: study.rows.iter().map(|r| r.row.label.clone()).collect(),
        key: study.key.clone(),
        columns: study.columns.clone(),
        seeds: s.seeds.clone(),
        episodes: s.episodes,
        cells,
        best_of_last: k,
        best_per_cell,
        runs,
        missing,
        other_lines: entries.len() - mine.len(),
    })
}

/// Write `report.json`, `table.md`, `success.png` (and, with best-per-cell cells,
/// `success-best-per-cell.png`) into `out`, a new or empty directory.
pub fn write_report<T: Task>(
    task: &T,
    report: &LogReport<T::Config>,
    x_label: &str,
    out: &Path,
) -> Result<()> {
    prepare_out(out)?;
    write_atomically(
        &out.join("report.json"),
        serde_json::to_string_pretty(report)?.as_bytes(),
    )?;
    write_atomically(&out.join("table.md"), report.table().as_bytes())?;
    plot_study(
        &task.title(&report.study),
        x_label,
        &report.labels,
        &report.columns,
        &report.cells,
        &report.best_per_cell,
        out,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::study::ballplate::{BallPlateTask, DemoConfig};
    use crate::study::{Policy, Row, Settings, StudyRow};
    use pir2_backends::config::{ModelConfig, Spec};
    use pir2_backends::train::TrainConfig;
    use pir2_runtime::LockstepTiming;
    use pir2_sim::dataset::Episode;

    /// The ball-plate task with the best-per-cell protocol at depth `1` (its own settings
    /// leave it off).
    struct WithBest(BallPlateTask, usize);

    impl Task for WithBest {
        type Env = <BallPlateTask as Task>::Env;
        type Config = DemoConfig;
        fn config(&self) -> &DemoConfig {
            self.0.config()
        }
        fn settings(&self) -> Settings {
            Settings {
                best_of_last: self.1,
                ..self.0.settings()
            }
        }
        fn spec(&self) -> Spec {
            self.0.spec()
        }
        fn period_ns(&self) -> u64 {
            self.0.period_ns()
        }
        fn make_env(&self) -> Result<Self::Env> {
            self.0.make_env()
        }
        fn model(&self, p: Policy) -> ModelConfig {
            self.0.model(p)
        }
        fn optimiser(&self) -> TrainConfig {
            self.0.optimiser()
        }
        fn rows(&self) -> Vec<Row> {
            self.0.rows()
        }
        fn demonstrations(&self, out: &Path) -> Result<Vec<Episode>> {
            self.0.demonstrations(out)
        }
        fn title(&self, s: &str) -> String {
            self.0.title(s)
        }
        /// Flow's cells also count under [`EQUIVALENT`] (a config that trains and evaluates
        /// flow the same way).
        fn equivalent_fingerprints(&self, p: Policy) -> Result<Vec<String>> {
            Ok(match p {
                Policy::Flow => vec![EQUIVALENT.to_string()],
                _ => Vec::new(),
            })
        }
    }

    const EQUIVALENT: &str = "00000000e0e0e0e0";

    /// Seeds 0 and 1, d0 ∈ {1, 2}, 10 episodes, 100 steps in 5 checkpoints (steps 20, 40,
    /// …, 100), best of the last 2.
    fn task() -> WithBest {
        WithBest(
            BallPlateTask::new(DemoConfig {
                seeds: vec![0, 1],
                d0s: vec![1, 2],
                episodes: 10,
                steps: 100,
                checkpoints: 5,
                ..DemoConfig::default()
            }),
            2,
        )
    }

    /// Flow's first row over d0, and πR² (n = 2) measured once for every column.
    fn study(t: &WithBest) -> Study {
        let rows = t.rows();
        let flow = rows.iter().find(|r| r.policy == Policy::Flow).unwrap();
        let pir2 = rows.iter().find(|r| r.policy == Policy::PiR2).unwrap();
        let mut s = Study::deployment(vec![flow.clone()], &[1, 2]);
        s.rows.push(StudyRow {
            row: pir2.clone(),
            sweep: Sweep::Once(LockstepTiming::zero_latency()),
        });
        s
    }

    fn line(
        config: &str,
        checkpoint: &str,
        label: &str,
        column: Option<usize>,
        seed: u64,
    ) -> String {
        line_n(config, checkpoint, label, column, seed, 10, 0)
    }

    fn line_n(
        config: &str,
        checkpoint: &str,
        label: &str,
        column: Option<usize>,
        seed: u64,
        episodes: usize,
        successes: usize,
    ) -> String {
        serde_json::json!({
            "config": config, "checkpoint": checkpoint, "label": label, "column": column,
            "seed": seed, "episodes": episodes, "successes": successes, "overruns": 0,
        })
        .to_string()
    }

    /// A log holding every cell of [`study`], with `successes(checkpoint, column, seed)`.
    fn full_log(
        t: &WithBest,
        successes: impl Fn(&str, Option<usize>, u64) -> usize,
    ) -> Vec<String> {
        let fp = config_fingerprint(t.config()).unwrap();
        let s = study(t);
        let (flow, pir2) = (&s.rows[0].row.label, &s.rows[1].row.label);
        let mut lines = Vec::new();
        for seed in [0, 1] {
            // flow chose step 40: the protocol takes steps 100 and 80; πR² chose the last
            // step: it takes 80 and 60.
            for c in [
                format!("flow-seed{seed}/best@40#wa{seed}"),
                format!("flow-seed{seed}/step-000100#wb{seed}"),
                format!("flow-seed{seed}/step-000080#wc{seed}"),
            ] {
                for col in [1, 2] {
                    let n = successes(&c, Some(col), seed);
                    lines.push(line_n(&fp, &c, flow, Some(col), seed, 10, n));
                }
            }
            for c in [
                format!("pir2-seed{seed}/best@100#wd{seed}"),
                format!("pir2-seed{seed}/step-000080#we{seed}"),
                format!("pir2-seed{seed}/step-000060#wf{seed}"),
            ] {
                lines.push(line_n(
                    &fp,
                    &c,
                    pir2,
                    None,
                    seed,
                    10,
                    successes(&c, None, seed),
                ));
            }
        }
        lines
    }

    fn write(dir: &Path, lines: &[String]) -> std::path::PathBuf {
        std::fs::create_dir_all(dir).unwrap();
        let p = dir.join("cells.jsonl");
        std::fs::write(&p, lines.join("\n") + "\n").unwrap();
        p
    }

    fn tmp(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("pir2-report-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    fn find(cells: &[Cell], label: &str, col: usize, seed: u64) -> usize {
        cells
            .iter()
            .find(|c| c.label == label && c.d0 == col && c.seed == seed)
            .unwrap_or_else(|| panic!("no cell {label} {col} {seed}"))
            .successes
    }

    #[test]
    fn checkpoint_steps_are_the_trainers() {
        assert_eq!(checkpoint_steps(100, 5), vec![20, 40, 60, 80, 100]);
        assert_eq!(checkpoint_steps(10, 3), vec![3, 6, 9, 10]);
        assert_eq!(checkpoint_steps(20_000, 10).len(), 10);
    }

    #[test]
    fn the_report_takes_the_chosen_and_the_protocols_steps_and_nothing_else() {
        let t = task();
        let s = study(&t);
        let (flow, pir2) = (s.rows[0].row.label.clone(), s.rows[1].row.label.clone());
        // Chosen 3; the protocol's steps 100 / 80 give 5 / 4 (seed 0) and 2 / 3 (seed 1).
        // πR²: chosen 4, step 80 ties at 4, step 60 has 2: the chosen cell stays.
        let mut lines = full_log(&t, |c, col, seed| {
            match (c.split('/').nth(1).unwrap(), seed) {
                (b, _) if b.starts_with("best@40") => 3 + col.unwrap_or(0) % 2,
                (b, 0) if b.starts_with("step-000100") => 5,
                (b, 0) if b.starts_with("step-000080") && c.starts_with("flow") => 4,
                (b, 1) if b.starts_with("step-000100") => 2,
                (b, 1) if b.starts_with("step-000080") && c.starts_with("flow") => 3,
                (b, _) if b.starts_with("best@100") || b.starts_with("step-000080") => 4,
                _ => 2,
            }
        });
        let fp = config_fingerprint(t.config()).unwrap();
        // Not the protocol's: an early step (a diagnostic look), another config, another
        // episode count, a batched cell.
        lines.push(line_n(
            &fp,
            "flow-seed0/step-000020#wz",
            &flow,
            Some(1),
            0,
            10,
            9,
        ));
        lines.push(line_n(
            "0123456789abcdef",
            "flow-seed0/best@40#wa0",
            &flow,
            Some(1),
            0,
            10,
            9,
        ));
        lines.push(line_n(
            &fp,
            "flow-seed0/best@40#wa0",
            &flow,
            Some(1),
            0,
            20,
            19,
        ));
        let mut batched: serde_json::Value = serde_json::from_str(&line_n(
            &fp,
            "flow-seed0/step-000100#wb0",
            &flow,
            Some(1),
            0,
            10,
            9,
        ))
        .unwrap();
        batched["eval"] = "batched g100 k2".into();
        lines.push(batched.to_string());
        let dir = tmp("protocol");
        let log = write(&dir, &lines);
        let before = std::fs::read(&log).unwrap();
        let r = report(&t, &s, &[log.as_path()], false).unwrap();
        assert_eq!(
            r.other_lines, 3,
            "the early step is of this config, the rest not"
        );
        assert!(r.missing.is_empty());
        assert_eq!(r.cells.len(), 2 * 2 * 2);
        assert_eq!(find(&r.cells, &flow, 1, 0), 4);
        assert_eq!(find(&r.cells, &flow, 2, 0), 3);
        assert_eq!(find(&r.best_per_cell, &flow, 1, 0), 5);
        assert_eq!(find(&r.best_per_cell, &flow, 2, 1), 3);
        assert_eq!(
            find(&r.best_per_cell, &flow, 1, 1),
            4,
            "the chosen 4 beats 2 and 3"
        );
        // The once-measured row is the same cell in every column.
        for col in [1, 2] {
            assert_eq!(find(&r.cells, &pir2, col, 0), 4);
            assert_eq!(find(&r.best_per_cell, &pir2, col, 1), 4);
        }
        let flow0 = r.runs.iter().find(|c| c.run == "flow-seed0").unwrap();
        assert_eq!(flow0.chosen.as_deref(), Some("flow-seed0/best@40#wa0"));
        assert_eq!(
            flow0.others,
            vec![
                (100, Some("flow-seed0/step-000100#wb0".to_string())),
                (80, Some("flow-seed0/step-000080#wc0".to_string())),
            ]
        );
        let table = r.table();
        assert!(table.contains("| policy / mode (seeds 0 / 1) |"), "{table}");
        assert!(
            table.contains(&format!("| {flow} | 0.40 / 0.40 | 0.30 / 0.30 |")),
            "{table}"
        );
        assert_eq!(std::fs::read(&log).unwrap(), before, "the log is only read");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The baselines' cells of another log, logged under a config equivalent for them, give
    /// the report the one log of everything gives; that log's cells of other policies are
    /// not taken (they ran another network).
    #[test]
    fn a_baselines_cells_count_under_an_equivalent_config_from_another_log() {
        let t = task();
        let s = study(&t);
        let pir2 = s.rows[1].row.label.clone();
        let fp = config_fingerprint(t.config()).unwrap();
        let full = full_log(&t, |c, col, seed| {
            (c.len() + col.unwrap_or(0) + seed as usize) % 10
        });
        let dir = tmp("equivalent");
        let whole = write(&dir.join("whole"), &full);
        let whole = report(&t, &s, &[whole.as_path()], false).unwrap();
        let (flow, own): (Vec<String>, Vec<String>) =
            full.into_iter().partition(|l| l.contains("\"flow-seed"));
        let mut other: Vec<String> = flow.iter().map(|l| l.replace(&fp, EQUIVALENT)).collect();
        // Another network under the same name as the study's chosen πR² checkpoint: were it
        // taken, the report would refuse two sets of weights under one name.
        other.push(line_n(
            EQUIVALENT,
            "pir2-seed0/best@100#wother",
            &pir2,
            None,
            0,
            10,
            9,
        ));
        let (a, b) = (write(&dir.join("a"), &own), write(&dir.join("b"), &other));
        let r = report(&t, &s, &[a.as_path(), b.as_path()], false).unwrap();
        assert_eq!(r.cells, whole.cells);
        assert_eq!(r.best_per_cell, whole.best_per_cell);
        assert_eq!(r.other_lines, 1);
        let e = report(&t, &s, &[a.as_path()], false)
            .unwrap_err()
            .to_string();
        assert!(e.contains("lacks") && e.contains("flow-seed0"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_missing_cell_is_named_unless_the_report_is_partial() {
        let t = task();
        let s = study(&t);
        let flow = s.rows[0].row.label.clone();
        let lines: Vec<String> = full_log(&t, |_, _, _| 1)
            .into_iter()
            .filter(|l| !(l.contains("flow-seed1/step-000080") && l.contains("\"column\":2")))
            .filter(|l| !l.contains("pir2-seed1/best"))
            .collect();
        let dir = tmp("missing");
        let log = write(&dir, &lines);
        let e = report(&t, &s, &[log.as_path()], false)
            .unwrap_err()
            .to_string();
        assert!(e.contains("lacks 2 cells"), "{e}");
        assert!(
            e.contains(&format!("{flow}, d0=2, seed 1: flow-seed1/step-000080")),
            "{e}"
        );
        assert!(e.contains("no chosen checkpoint of pir2-seed1"), "{e}");
        assert!(e.contains("--partial"), "{e}");
        let r = report(&t, &s, &[log.as_path()], true).unwrap();
        assert_eq!(r.missing.len(), 2, "{:?}", r.missing);
        // Seed 1's πR² cells are gone from both tables, flow's d0 = 2 cell only from the
        // best-per-cell one.
        assert_eq!(r.cells.len(), 8 - 2);
        assert_eq!(r.best_per_cell.len(), 8 - 3);
        assert!(r.table().contains("Partial: 2 cells"), "{}", r.table());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn two_sets_of_weights_under_one_name_are_refused_by_name() {
        let t = task();
        let s = study(&t);
        let fp = config_fingerprint(t.config()).unwrap();
        let mut lines = full_log(&t, |_, _, _| 1);
        lines.push(line(
            &fp,
            "flow-seed0/best@40#wother",
            &s.rows[0].row.label,
            Some(1),
            0,
        ));
        let dir = tmp("ambiguous");
        let log = write(&dir, &lines);
        let e = report(&t, &s, &[log.as_path()], true)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("flow-seed0/best@40#wa0") && e.contains("flow-seed0/best@40#wother"),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_log_of_another_config_is_refused_naming_both_fingerprints() {
        let t = task();
        let s = study(&t);
        let lines = vec![line(
            "0123456789abcdef",
            "flow-seed0/best@40#wa",
            "x",
            Some(1),
            0,
        )];
        let dir = tmp("other");
        let log = write(&dir, &lines);
        let e = report(&t, &s, &[log.as_path()], true)
            .unwrap_err()
            .to_string();
        let fp = config_fingerprint(t.config()).unwrap();
        assert!(e.contains("0123456789abcdef") && e.contains(&fp), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
