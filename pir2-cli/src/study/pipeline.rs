//! The one pipeline every [`Task`] runs: demonstrations → train each `(policy, seed)` with
//! closed-loop checkpoint validation → evaluate rows × seeds × columns through the lock-step
//! runtime → `result.json`, `table.md`, `success.png`.
//!
//! One file on purpose: the stages in the order a study runs them (training jobs, the resumable
//! training directory and its data check, the run, the outputs), with their tests; the closed
//! loop and the evaluation they call are [`super::closed_loop`] and [`super::evaluate`].
//!
//! There is one closed loop ([`closed_loop`]); what runs the action head comes from a
//! [`Models`] factory: a local candle model, or a remote one (`pir2 eval --remote`).

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use anyhow::{bail, Context, Result};

use pir2_backends::candle::{with_kernel_pool, CandleModel};
use pir2_backends::config::Config;
use pir2_backends::train::{compute_stats, Dataset, Progress, TrainConfig, Trainer};
use pir2_sim::dataset::Episode;

pub use super::closed_loop::{
    closed_loop, head_spec, output_map, policy_dir, EvalPath, Models, Trained,
};
pub use super::evaluate::{
    chosen_checkpoint, config_fingerprint, earlier_config_fingerprints, evaluate,
    evaluate_best_per_cell, last_step_checkpoints, total_episodes, trained_dir, CellLog, Logged,
};
use super::evaluate::{fnv1a, FNV_OFFSET};
pub use super::output::{bar, log_line, prepare_out, write_atomically};
use super::report::task_checkpoint_steps;
use super::{Policy, Scores, Settings, Study, StudyResult, Task};
use crate::plot::plot_series;

/// Sim episodes as a training dataset.
#[derive(Debug)]
pub struct Episodes<'a>(pub &'a [Episode]);

impl Dataset for Episodes<'_> {
    fn num_episodes(&self) -> usize {
        self.0.len()
    }
    fn episode_len(&self, e: usize) -> usize {
        self.0[e].len()
    }
    fn fast(&self, e: usize, t: usize) -> &[f32] {
        self.0[e].fast(t)
    }
    fn slow(&self, e: usize, t: usize) -> &[f32] {
        self.0[e].slow(t)
    }
    fn action(&self, e: usize, t: usize) -> &[f32] {
        self.0[e].action(t)
    }
}

/// Train `policy` on `demos` (seeded); the checkpoint is chosen by closed-loop validation
/// ([`Task::validation`]). With `out_dir`, step checkpoints,
/// `loss.jsonl` and `best.json` are written there. `on_step` sees the optimiser step.
pub fn train_policy<T: Task>(
    task: &T,
    demos: &[Episode],
    policy: Policy,
    seed: u64,
    out_dir: Option<&Path>,
    on_step: &dyn Fn(usize),
) -> Result<(CandleModel, Scores)> {
    train_policy_resumable(task, demos, policy, seed, out_dir, false, on_step)
}

/// [`train_policy`], continuing from the last step checkpoint in `out_dir` when `resume`
/// (the validation scores returned are those of this run's checkpoints).
pub fn train_policy_resumable<T: Task>(
    task: &T,
    demos: &[Episode],
    policy: Policy,
    seed: u64,
    out_dir: Option<&Path>,
    resume: bool,
    on_step: &dyn Fn(usize),
) -> Result<(CandleModel, Scores)> {
    let spec = task.spec();
    let stats = compute_stats(&Episodes(demos), &spec)?;
    let config = Config {
        spec,
        model: task.model(policy),
    };
    let mut model = CandleModel::new(config, stats, seed)?;
    // Recorded in every checkpoint's identity.json: evaluating it as another policy is refused.
    model.set_policy(Some(policy));
    let s = task.settings();
    let base = task.optimiser();
    let tc = TrainConfig {
        seed,
        schedule: policy.schedule(&s.recipe),
        checkpoint_every: Some(checkpoint_every(base.steps, s.checkpoints)),
        ..base
    };
    let (val_mode, val_timing) = task.validation(policy);
    let val_seed = 1_000_000 + seed;
    let mut meter = ProgressMeter::new(Instant::now());
    let on_progress = |p: &Progress| {
        on_step(p.step);
        if let Some((mean_loss, rate)) = meter.step(p.step, p.steps, p.loss, Instant::now()) {
            log_line(&format!(
                "  {policy:?} seed {seed}: step {}/{}, mean loss {mean_loss:.4}, {rate:.1} steps/s",
                p.step, p.steps,
            ));
        }
    };
    let mut scores = Vec::new();
    // Ctrl-C / SIGTERM: the training state of the step reached is saved (with an output
    // directory) and the run ends with an error saying `--resume` continues from there.
    let mut trainer = Trainer::new(tc)
        .stop_on(crate::signals::stop_flag())
        .on_progress(on_progress)
        .validate(|m, step| {
            let ok = Models::local(m)
                .and_then(|models| {
                    closed_loop(
                        task,
                        &models,
                        policy,
                        &val_mode,
                        val_timing,
                        s.val_episodes,
                        val_seed,
                        EvalPath::Threads(1),
                        &|| {},
                    )
                })
                .map(|r| r.0)
                .unwrap_or(0); // an error counts as no success
            let at = if val_timing == pir2_runtime::LockstepTiming::zero_latency() {
                // The zero-delay variants: they run without latency.
                "zero latency".to_string()
            } else {
                format!("d0 = {}", s.val_d0)
            };
            log_line(&format!(
                "  {policy:?} seed {seed}: checkpoint validation {ok}/{} at {at}",
                s.val_episodes
            ));
            let rate = ok as f64 / s.val_episodes.max(1) as f64;
            scores.push((step, rate));
            rate
        });
    trainer = trainer.later_ties(s.later_ties);
    if let Some(d) = out_dir {
        trainer = trainer.out_dir(d).resume(resume);
    }
    trainer.run(&mut model, &Episodes(demos))?;
    Ok((model, scores))
}

/// Training steps between two step checkpoints of a run of `steps` steps that writes
/// `checkpoints` of them (the trainer also writes one at the last step).
pub fn checkpoint_every(steps: usize, checkpoints: usize) -> usize {
    (steps / checkpoints.max(1)).max(1)
}

/// Run `train(job index, policy, seed)` for every job on `threads` worker threads (jobs are
/// taken in order; each is seeded on its own, so the result does not depend on `threads`).
/// Returns the results in job order.
pub fn train_jobs<P, T>(
    jobs: &[(P, u64)],
    threads: usize,
    train: impl Fn(usize, P, u64) -> Result<T> + Sync,
) -> Result<Vec<T>>
where
    P: Copy + Sync,
    T: Send,
{
    let next = AtomicUsize::new(0);
    let workers = threads.clamp(1, jobs.len().max(1));
    // Each job's kernels run on a pool of their own with the global pool's thread count
    // (same bits), so that side-by-side jobs do not queue on one shared pool, which cost
    // them about a quarter of their speed (see `with_kernel_pool`).
    let train = &train;
    let results: Vec<Result<Vec<(usize, T)>>> = std::thread::scope(|s| {
        let hs: Vec<_> = (0..workers)
            .map(|_| {
                s.spawn(|| -> Result<Vec<(usize, T)>> {
                    let mut mine = Vec::new();
                    loop {
                        let j = next.fetch_add(1, Ordering::SeqCst);
                        if j >= jobs.len() {
                            return Ok(mine);
                        }
                        let (policy, seed) = jobs[j];
                        let t = with_kernel_pool(|| train(j, policy, seed))??;
                        mine.push((j, t));
                    }
                })
            })
            .collect();
        hs.into_iter()
            .map(|h| h.join().expect("training thread panicked"))
            .collect()
    });
    let mut out: Vec<Option<T>> = (0..jobs.len()).map(|_| None).collect();
    let mut errors = Vec::new();
    for r in results {
        match r {
            Ok(done) => {
                for (j, t) in done {
                    out[j] = Some(t);
                }
            }
            Err(e) => errors.push(e),
        }
    }
    // Every worker's error is reported (two policies stopped by one Ctrl-C each saved a
    // state, and the message must name both), in one error.
    let mut errors = errors.into_iter();
    if let Some(first) = errors.next() {
        let rest: Vec<String> = errors.map(|e| format!("{e:#}")).collect();
        if rest.is_empty() {
            return Err(first);
        }
        bail!("{first:#}; and {}", rest.join("; and "));
    }
    Ok(out.into_iter().map(|t| t.expect("every job ran")).collect())
}

/// With the settings' `pretrained` and without `train_missing`: an error naming every
/// `policy × seed` of `policies` × the settings' seeds whose run in `pretrained` has no
/// chosen checkpoint (`<policy>-seed<s>/best`), instead of training it unasked. A mistyped
/// `--checkpoint` or an evaluation started before its runs finished would otherwise start
/// hours of training into the study's output directory.
pub fn refuse_missing_pretrained(s: &Settings, policies: &[Policy]) -> Result<()> {
    let Some(dir) = s.pretrained.as_deref().filter(|_| !s.train_missing) else {
        return Ok(());
    };
    let missing: Vec<String> = s
        .seeds
        .iter()
        .flat_map(|&seed| policies.iter().map(move |&p| policy_dir(p, seed)))
        .filter(|run| !dir.join(run).join("best").is_dir())
        .collect();
    if !missing.is_empty() {
        let them = if missing.len() == 1 { "it" } else { "them" };
        bail!(
            "{dir} holds no trained {runs} (no `best/` checkpoint); finish {them} with `pir2 \
             train … --out {dir}`, list only trained policies and seeds in the config, or \
             train {them} into this study's output with --train-missing",
            dir = dir.display(),
            runs = missing.join(", "),
        );
    }
    Ok(())
}

/// Before anything is measured: with the settings' `best_of_last` > 0, every finished run in
/// the settings' `pretrained` must have the step checkpoints the best-per-cell protocol takes
/// ([`last_step_checkpoints`]: an error naming the first run that lacks some). A run restored
/// from its saved state has only `best/`; refused at the end, its chosen cells would have
/// been measured for nothing.
pub fn refuse_missing_step_checkpoints<T: Task>(task: &T, policies: &[Policy]) -> Result<()> {
    let s = task.settings();
    let Some(dir) = s.pretrained.as_deref().filter(|_| s.best_of_last > 0) else {
        return Ok(());
    };
    let steps = task_checkpoint_steps(task);
    for &seed in &s.seeds {
        for &p in policies {
            let run = dir.join(policy_dir(p, seed));
            if run.join("best").is_dir() {
                last_step_checkpoints(&run, &steps, s.best_of_last)?;
            }
        }
    }
    Ok(())
}

/// Train (or load from the settings' `pretrained`) every policy × seed on the worker
/// threads; each trained policy's run goes to `ckpt_root/<policy>-seed<s>/` and its chosen
/// checkpoint to `.../best`. A run missing from `pretrained` is trained only with the
/// settings' `train_missing` ([`refuse_missing_pretrained`]). `only_seeds` narrows the
/// settings' seeds (each must be one of them); the jobs keep the settings' seed-major order.
pub fn train_all<T: Task>(
    task: &T,
    demos: &[Episode],
    policies: &[Policy],
    only_seeds: Option<&[u64]>,
    ckpt_root: &Path,
    resume: bool,
) -> Result<Vec<Trained>> {
    let s = task.settings();
    refuse_missing_pretrained(&s, policies)?;
    let steps = task.optimiser().steps;
    let seeds = select_seeds(&s.seeds, only_seeds)?;
    let jobs: Vec<(Policy, u64)> = seeds
        .iter()
        .flat_map(|&seed| policies.iter().map(move |&p| (p, seed)))
        .collect();
    let pb = bar(
        (jobs.len() * steps) as u64,
        &format!("training {} policies", jobs.len()),
    );
    let done = AtomicUsize::new(0);
    let models = train_jobs(&jobs, s.threads, |i, policy, seed| {
        if let Some(dir) = &s.pretrained {
            let best = dir.join(policy_dir(policy, seed)).join("best");
            if best.exists() {
                let model = CandleModel::load_expect(&best, &task.spec())
                    .with_context(|| format!("loading {}", best.display()))?;
                crate::identity::expect_policy(&model, &best, policy, "loading it as")?;
                log_line(&format!(
                    "loaded {policy:?} seed {seed} from {}",
                    best.display()
                ));
                return Ok((model, Vec::new(), dir.join(policy_dir(policy, seed))));
            }
        }
        let t = Instant::now();
        let ckpt = ckpt_root.join(policy_dir(policy, seed));
        let best = ckpt.join("best");
        if resume && best.exists() {
            let model = CandleModel::load_expect(&best, &task.spec())
                .with_context(|| format!("loading {}", best.display()))?;
            crate::identity::expect_policy(&model, &best, policy, "loading it as")?;
            log_line(&format!(
                "{policy:?} seed {seed} finished in an earlier run: kept {}",
                best.display()
            ));
            pb.set_position((done.fetch_add(1, Ordering::SeqCst) + 1) as u64 * steps as u64);
            return Ok((model, Vec::new(), ckpt));
        }
        let (model, scores) =
            train_policy_resumable(task, demos, policy, seed, Some(&ckpt), resume, &|_| {})?;
        model.save(&best)?;
        pb.set_position((done.fetch_add(1, Ordering::SeqCst) + 1) as u64 * steps as u64);
        log_line(&format!(
            "trained {policy:?} seed {seed} ({}/{}) in {:.0} s; closed-loop validation (step, success): {scores:?}",
            i + 1,
            jobs.len(),
            t.elapsed().as_secs_f64()
        ));
        Ok((model, scores, ckpt))
    })?;
    pb.finish();
    Ok(jobs
        .into_iter()
        .zip(models)
        .map(|((policy, seed), (model, scores, dir))| Trained {
            policy,
            seed,
            model,
            scores,
            dir,
        })
        .collect())
}

/// Run `study` on `task` into `out` (a new directory): demonstrations, training (checkpoints
/// under `out/checkpoints/`), evaluation; writes `result.json`, `table.md`, `success.png`
/// (and, with the settings' `best_of_last` > 0, the best-checkpoint-per-cell cells, their
/// table in `table.md` and `success-best-per-cell.png`). Every cell is appended to
/// `out/cells.jsonl` as soon as it is measured; with `resume`, `out` is an interrupted run
/// of the same config and its logged cells are reused ([`CellLog`]; the task's
/// demonstrations must then not write into `out`). SIGINT or SIGTERM
/// ([`crate::signals::stop_flag`]) ends the evaluation with an error before its next cell
/// ([`CellLog::stop_on`]).
pub fn run<T: Task>(
    task: &T,
    study: &Study,
    out: &Path,
    resume: bool,
) -> Result<StudyResult<T::Config>> {
    // Before anything is loaded or written: a listed run missing from `pretrained`.
    refuse_missing_pretrained(&task.settings(), &study.policies())?;
    refuse_missing_step_checkpoints(task, &study.policies())?;
    if resume {
        std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    } else {
        prepare_out(out)?;
    }
    let log = CellLog::open(
        out,
        config_fingerprint(task.config())?,
        &earlier_config_fingerprints(task.config())?,
        resume,
    )?;
    let t0 = Instant::now();
    let mut timings = Vec::new();
    let demos = task.demonstrations(out)?;
    timings.push(("collect".to_string(), t0.elapsed().as_secs_f64()));

    let t1 = Instant::now();
    let trained = train_all(
        task,
        &demos,
        &study.policies(),
        None,
        &out.join("checkpoints"),
        resume,
    )?;
    timings.push(("train".to_string(), t1.elapsed().as_secs_f64()));

    let t2 = Instant::now();
    let pb = bar(
        total_episodes(task, study) as u64,
        &format!("evaluating ({} study)", study.name),
    );
    let local = trained
        .iter()
        .map(|t| Ok((t.policy, t.seed, Models::local(&t.model)?)))
        .collect::<Result<Vec<_>>>()?;
    let checkpoint = |p, s| chosen_checkpoint(&trained_dir(&trained, p, s));
    // SIGINT / SIGTERM end the evaluation between cells (the log keeps what was measured);
    // the handlers are installed here, as training installs them, not during collection.
    let log = log.stop_on(crate::signals::stop_flag());
    let logged = Logged {
        log: &log,
        checkpoint: &checkpoint,
    };
    let cells = evaluate(
        task,
        study,
        &|p, s| {
            &local
                .iter()
                .find(|m| m.0 == p && m.1 == s)
                .expect("every policy of the study was trained")
                .2
        },
        Some(&logged),
        &pb,
    )?;
    pb.finish();
    timings.push(("evaluate".to_string(), t2.elapsed().as_secs_f64()));
    let k = task.settings().best_of_last;
    let best_per_cell = if k > 0 {
        let t3 = Instant::now();
        let pb = bar(
            (k * total_episodes(task, study)) as u64,
            &format!("best checkpoint per cell (last {k})"),
        );
        let best = evaluate_best_per_cell(task, study, &trained, k, &cells, Some(&log), &pb)?;
        pb.finish();
        timings.push(("best per cell".to_string(), t3.elapsed().as_secs_f64()));
        best
    } else {
        Vec::new()
    };
    timings.push(("total".to_string(), t0.elapsed().as_secs_f64()));
    let result = StudyResult {
        study: study.name.clone(),
        config: task.config().clone(),
        demos: demos.len(),
        labels: study.rows.iter().map(|r| r.row.label.clone()).collect(),
        key: study.key.clone(),
        columns: study.columns.clone(),
        cells,
        best_of_last: k,
        best_per_cell,
        validation: trained
            .iter()
            .map(|t| (t.policy, t.seed, t.scores.clone()))
            .collect(),
        timings,
    };
    write_outputs(task, &result, &study.x_label, out)?;
    Ok(result)
}

/// Train `policies` × the settings' seeds (or only `only_seeds` of them, [`train_all`]) into
/// `out` (a new directory):
/// `out/<policy>-seed<s>/` holds the step checkpoints, `loss.jsonl`, `best.json` and the
/// chosen checkpoint `best/`; the task's config is written to `out/config.toml` and what the
/// demonstrations were to `out/data.json` ([`DataFingerprint`]); `resume` refuses a different
/// config or different demonstrations by name.
pub fn train_into<T: Task>(
    task: &T,
    policies: &[Policy],
    only_seeds: Option<&[u64]>,
    out: &Path,
    resume: bool,
) -> Result<Vec<(Policy, u64, Scores)>> {
    let config = toml::to_string(task.config()).context("serialising the config")?;
    let config_file = out.join("config.toml");
    if resume {
        let before = std::fs::read_to_string(&config_file).with_context(|| {
            format!(
                "--resume: {} is not a training run to continue (no readable config.toml)",
                out.display()
            )
        })?;
        // Compared as configs, not as text: a field added later with its default does not
        // make an earlier run's config differ.
        let same = before == config
            || toml::from_str::<T::Config>(&before).is_ok_and(|b| &b == task.config());
        if !same {
            bail!(
                "--resume: the config differs from the one {} was trained with ({}); \
                 resume with that config or train into a new directory",
                out.display(),
                config_file.display()
            );
        }
    } else {
        prepare_out(out)?;
        write_atomically(&config_file, config.as_bytes())?;
    }
    let demos = task.demonstrations(out)?;
    check_data(&out.join(DATA_FILE), &demos, resume)?;
    let trained = train_all(task, &demos, policies, only_seeds, out, resume)?;
    Ok(trained
        .into_iter()
        .map(|t| (t.policy, t.seed, t.scores))
        .collect())
}

/// The settings' `seeds`, or the `only` of them in the settings' order; a seed of `only` that
/// the settings do not list is an error naming it (and the listed ones).
pub(crate) fn select_seeds(seeds: &[u64], only: Option<&[u64]>) -> Result<Vec<u64>> {
    let Some(only) = only else {
        return Ok(seeds.to_vec());
    };
    if let Some(s) = only.iter().find(|s| !seeds.contains(s)) {
        bail!("seed {s} is not one of the config's seeds {seeds:?}");
    }
    Ok(seeds.iter().copied().filter(|s| only.contains(s)).collect())
}

/// File in a training run's directory naming the demonstrations it trains on.
pub const DATA_FILE: &str = "data.json";

/// What a training run's demonstrations were: episode and frame counts and a fingerprint
/// (FNV-1a, 64 bits) of every value the trainer reads (per episode its length, then per
/// frame the fast and slow observations and the action, as little-endian `f32`).
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct DataFingerprint {
    /// Episodes.
    pub episodes: usize,
    /// Frames over all episodes.
    pub frames: usize,
    /// The fingerprint, 16 hex digits.
    pub fingerprint: String,
}

impl DataFingerprint {
    /// The fingerprint of `demos`.
    pub fn of(demos: &[Episode]) -> Self {
        let d = Episodes(demos);
        let mut h = FNV_OFFSET;
        let mut frames = 0;
        for e in 0..d.num_episodes() {
            let len = d.episode_len(e);
            frames += len;
            h = fnv1a(h, &(len as u64).to_le_bytes());
            for t in 0..len {
                for v in [d.fast(e, t), d.slow(e, t), d.action(e, t)] {
                    for x in v {
                        h = fnv1a(h, &x.to_le_bytes());
                    }
                }
            }
        }
        Self {
            episodes: d.num_episodes(),
            frames,
            fingerprint: format!("{h:016x}"),
        }
    }
}

/// Record the demonstrations of a new run in `file`, or with `resume` check that they are
/// the ones the run started on: demonstrations regenerated differently (another expert, or
/// a change that alters their numbers) must not continue a run silently. A run begun before
/// the file existed gets it now.
pub(crate) fn check_data(file: &Path, demos: &[Episode], resume: bool) -> Result<()> {
    let now = DataFingerprint::of(demos);
    let read = match std::fs::read_to_string(file) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        r => Some(r.with_context(|| format!("reading {}", file.display()))?),
    };
    if resume {
        if let Some(text) = read {
            let before: DataFingerprint = serde_json::from_str(&text).with_context(|| {
                format!("--resume: {} is not a data fingerprint", file.display())
            })?;
            if before != now {
                bail!(
                    "--resume: the demonstrations differ from the ones this run was trained on \
                     ({} episodes, {} frames, fingerprint {}; now {} episodes, {} frames, \
                     fingerprint {}, see {}); train into a new directory",
                    before.episodes,
                    before.frames,
                    before.fingerprint,
                    now.episodes,
                    now.frames,
                    now.fingerprint,
                    file.display()
                );
            }
            return Ok(());
        }
    }
    write_atomically(file, serde_json::to_string_pretty(&now)?.as_bytes())
}

/// Write `result.json`, `table.md` and `success.png` into `out`. The JSON and the table are
/// written atomically, so an interrupted write leaves the previous file whole, never a
/// truncated one.
pub fn write_outputs<T: Task>(
    task: &T,
    result: &StudyResult<T::Config>,
    x_label: &str,
    out: &Path,
) -> Result<()> {
    let json = serde_json::to_string_pretty(result)?;
    write_atomically(&out.join("result.json"), json.as_bytes())?;
    write_atomically(&out.join("table.md"), result.table().as_bytes())?;
    plot_study(
        &task.title(&result.study),
        x_label,
        &result.labels,
        &result.columns,
        &result.cells,
        &result.best_per_cell,
        out,
    )
}

/// `success.png` of `cells` (the chosen checkpoints) in `out`, and with `best_per_cell`
/// cells `success-best-per-cell.png` beside it.
pub fn plot_study(
    title: &str,
    x_label: &str,
    labels: &[String],
    columns: &[usize],
    cells: &[super::Cell],
    best_per_cell: &[super::Cell],
    out: &Path,
) -> Result<()> {
    let series = super::to_series(cells, labels, columns);
    plot_series(
        &out.join("success.png"),
        title,
        x_label,
        "success rate",
        &series,
    )?;
    if !best_per_cell.is_empty() {
        let series = super::to_series(best_per_cell, labels, columns);
        plot_series(
            &out.join("success-best-per-cell.png"),
            &format!("{title} (best checkpoint per cell)"),
            x_label,
            "success rate",
            &series,
        )?;
    }
    Ok(())
}

/// The numbers of a training progress line, printed every 100 steps and at the last one:
/// the mean loss of the steps since the previous line and the steps per second of this
/// sitting. Both count only the steps this process ran, so a resumed run does not report
/// the resumed-from steps as done in no time, nor spread a partial window's loss over 100.
struct ProgressMeter {
    t0: Instant,
    first: Option<usize>,
    loss_sum: f64,
    in_window: usize,
}

impl ProgressMeter {
    fn new(t0: Instant) -> Self {
        Self {
            t0,
            first: None,
            loss_sum: 0.0,
            in_window: 0,
        }
    }

    /// Record step `step` (1-based) of `steps`; `Some((mean loss, steps/s))` when a line is due.
    fn step(&mut self, step: usize, steps: usize, loss: f32, now: Instant) -> Option<(f64, f64)> {
        let first = *self.first.get_or_insert(step);
        self.loss_sum += loss as f64;
        self.in_window += 1;
        if step % 100 != 0 && step != steps {
            return None;
        }
        let mean = self.loss_sum / self.in_window as f64;
        let done = (step + 1 - first) as f64;
        let rate = done / now.duration_since(self.t0).as_secs_f64().max(1e-9);
        self.loss_sum = 0.0;
        self.in_window = 0;
        Some((mean, rate))
    }
}

#[cfg(test)]
mod tests {
    use super::{
        check_data, refuse_missing_pretrained, select_seeds, train_jobs, DataFingerprint, Policy,
        ProgressMeter, Settings,
    };
    use pir2_sim::dataset::Episode;

    #[test]
    fn only_seeds_narrow_the_configs_seeds_in_their_order_and_refuse_others_by_name() {
        let all = [0, 1, 2];
        assert_eq!(select_seeds(&all, None).unwrap(), vec![0, 1, 2]);
        assert_eq!(select_seeds(&all, Some(&[2, 0])).unwrap(), vec![0, 2]);
        let e = select_seeds(&all, Some(&[1, 5])).unwrap_err().to_string();
        assert!(e.contains("seed 5") && e.contains("[0, 1, 2]"), "{e}");
    }

    #[test]
    fn a_resumed_run_refuses_other_demonstrations_by_name() {
        let dir = std::env::temp_dir().join(format!("pir2-data-fp-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("data.json");
        let demos = |last: f32| {
            let mut e = Episode::new(2, 1, 1);
            e.push(&[0.5, 1.0], &[2.0], &[0.25]);
            e.push(&[0.5, 1.5], &[2.0], &[last]);
            vec![e]
        };
        check_data(&file, &demos(0.5), false).unwrap();
        let written = std::fs::read_to_string(&file).unwrap();
        assert!(written.contains("\"frames\": 2"), "{written}");
        // The same data resume; one changed value does not, and the file is kept.
        check_data(&file, &demos(0.5), true).unwrap();
        let e = check_data(&file, &demos(0.5000001), true)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("demonstrations differ") && e.contains("data.json"),
            "{e}"
        );
        assert_eq!(std::fs::read_to_string(&file).unwrap(), written);
        assert_ne!(
            DataFingerprint::of(&demos(0.5)).fingerprint,
            DataFingerprint::of(&demos(0.5000001)).fingerprint
        );
        // A run from before the file existed gets it on resume.
        std::fs::remove_file(&file).unwrap();
        check_data(&file, &demos(0.5), true).unwrap();
        assert_eq!(std::fs::read_to_string(&file).unwrap(), written);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_run_missing_from_the_trained_policies_is_refused_by_name_unless_asked() {
        let dir = std::env::temp_dir().join(format!("pir2-pretrained-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("flow-seed0/best")).unwrap();
        // An unfinished run: step checkpoints, no chosen one.
        std::fs::create_dir_all(dir.join("rtc-seed0/step-002000")).unwrap();
        let mut s = Settings::from_config(2, 15, &[0, 1], 10, 2, 2, 1);
        let policies = [Policy::Flow, Policy::Rtc];
        // Nothing pretrained: nothing to refuse.
        refuse_missing_pretrained(&s, &policies).unwrap();
        s.pretrained = Some(dir.clone());
        let e = refuse_missing_pretrained(&s, &policies)
            .unwrap_err()
            .to_string();
        for run in ["rtc-seed0", "flow-seed1", "rtc-seed1", "--train-missing"] {
            assert!(e.contains(run), "{run}: {e}");
        }
        assert!(!e.contains("flow-seed0"), "{e}");
        // Only the trained ones listed: fine.
        s.seeds = vec![0];
        refuse_missing_pretrained(&s, &[Policy::Flow]).unwrap();
        // Asked to train what is missing: fine.
        s.seeds = vec![0, 1];
        s.train_missing = true;
        refuse_missing_pretrained(&s, &policies).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn every_failed_training_job_is_named_in_the_one_error() {
        let jobs = [(0u8, 0u64), (1, 0), (2, 0)];
        let r = train_jobs(&jobs, 3, |_, p, _| {
            if p == 1 {
                Ok(p)
            } else {
                anyhow::bail!("job {p} interrupted (state saved in interrupted-{p})")
            }
        });
        let e = format!("{:#}", r.unwrap_err());
        assert!(
            e.contains("interrupted-0") && e.contains("interrupted-2") && e.contains("; and "),
            "{e}"
        );
        let ok = train_jobs(&jobs, 2, |_, p, _| Ok(p)).unwrap();
        assert_eq!(ok, vec![0, 1, 2]);
    }
    use std::time::{Duration, Instant};

    #[test]
    fn a_resumed_run_reports_its_own_steps_and_the_mean_of_its_window() {
        let t0 = Instant::now();
        let mut m = ProgressMeter::new(t0);
        // Resumed after step 11150: 50 steps of loss 1.0 reach the line at 11200.
        for step in 11151..11200 {
            assert!(m.step(step, 20000, 1.0, t0).is_none());
        }
        let (mean, rate) = m
            .step(11200, 20000, 1.0, t0 + Duration::from_secs(25))
            .unwrap();
        assert_eq!(mean, 1.0);
        assert!((rate - 2.0).abs() < 1e-9, "{rate}");
        // The next window: 100 steps alternating 0.5 and 1.5 (mean 1.0).
        for step in 11201..11300 {
            let loss = if step % 2 == 0 { 0.5 } else { 1.5 };
            assert!(m.step(step, 20000, loss, t0).is_none());
        }
        let (mean, _) = m
            .step(11300, 20000, 0.5, t0 + Duration::from_secs(75))
            .unwrap();
        assert!((mean - 1.0).abs() < 1e-9, "{mean}");
        // The last step closes a partial window of one step.
        let (mean, rate) = m
            .step(11301, 11301, 3.0, t0 + Duration::from_secs(151))
            .unwrap();
        assert_eq!(mean, 3.0);
        assert!((rate - 1.0).abs() < 1e-9, "{rate}");
    }
}
