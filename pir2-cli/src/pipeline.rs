//! The stages every task's study shares (ball-on-plate demo, Leap cube): progress bars, a
//! fresh output directory, training with closed-loop checkpoint validation, training
//! `(policy, seed)` jobs on worker threads, and evaluating rows × seeds × columns into
//! [`Cell`]s. Task-specific parts (model config, optimiser settings, environment, timing)
//! are passed in as closures.

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};

use pir2_backends::candle::CandleModel;
use pir2_backends::train::{Dataset, Progress, TrainConfig, Trainer};
use pir2_runtime::Mode;

use crate::study::Cell;

/// Closed-loop validation scores of one training run: `(step, success rate)`.
pub type Scores = Vec<(usize, f64)>;

/// A progress bar with the studies' style.
pub fn bar(len: u64, msg: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    pb.set_style(
        ProgressStyle::with_template("{msg:<34} [{bar:30}] {pos}/{len} {elapsed_precise}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_message(msg.to_string());
    pb
}

/// Create `out`, refusing a directory that exists and is not empty.
pub fn prepare_out(out: &Path) -> Result<()> {
    if out.exists()
        && std::fs::read_dir(out)
            .map(|mut d| d.next().is_some())
            .unwrap_or(true)
    {
        bail!(
            "output directory {} exists and is not empty; choose another with --out",
            out.display()
        );
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))
}

/// Train `model` on `data` with `tc`; at every checkpoint `validate` runs the model in
/// closed loop and returns its successes out of `val_episodes` (an error counts as 0). The
/// trainer keeps the best checkpoint (the model holds it on return) and, with `out_dir`,
/// writes step checkpoints, `loss.jsonl` and `best.json` there.
pub fn train_validated<D: Dataset + ?Sized>(
    model: &mut CandleModel,
    data: &D,
    tc: TrainConfig,
    out_dir: Option<&Path>,
    on_progress: impl FnMut(&Progress),
    val_episodes: usize,
    validate: impl Fn(&CandleModel) -> Result<usize>,
) -> Result<Scores> {
    let mut scores = Vec::new();
    let mut trainer = Trainer::new(tc)
        .on_progress(on_progress)
        .validate(|m, step| {
            let ok = validate(m).unwrap_or(0);
            let s = ok as f64 / val_episodes.max(1) as f64;
            scores.push((step, s));
            s
        });
    if let Some(d) = out_dir {
        trainer = trainer.out_dir(d);
    }
    trainer.run(model, data)?;
    Ok(scores)
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
    let results: Vec<Result<Vec<(usize, T)>>> = std::thread::scope(|s| {
        let hs: Vec<_> = (0..threads.clamp(1, jobs.len().max(1)))
            .map(|_| {
                s.spawn(|| -> Result<Vec<(usize, T)>> {
                    let mut mine = Vec::new();
                    loop {
                        let j = next.fetch_add(1, Ordering::SeqCst);
                        if j >= jobs.len() {
                            return Ok(mine);
                        }
                        let (policy, seed) = jobs[j];
                        mine.push((j, train(j, policy, seed)?));
                    }
                })
            })
            .collect();
        hs.into_iter()
            .map(|h| h.join().expect("training thread panicked"))
            .collect()
    });
    let mut out: Vec<Option<T>> = (0..jobs.len()).map(|_| None).collect();
    for r in results {
        for (j, t) in r? {
            out[j] = Some(t);
        }
    }
    Ok(out.into_iter().map(|t| t.expect("every job ran")).collect())
}

/// Evaluate every row `(label, policy, mode)` × seed × column (in that order) with
/// `cell(policy, mode, seed, column) -> (successes, overruns)` over `episodes` episodes.
pub fn evaluate_rows<'r, P: Copy + 'r>(
    rows: impl IntoIterator<Item = (&'r str, P, &'r Mode)>,
    seeds: &[u64],
    columns: &[usize],
    episodes: usize,
    mut cell: impl FnMut(P, &Mode, u64, usize) -> Result<(usize, u64)>,
) -> Result<Vec<Cell>> {
    let mut cells = Vec::new();
    for (label, policy, mode) in rows {
        for &seed in seeds {
            for &col in columns {
                let (successes, overruns) = cell(policy, mode, seed, col)?;
                cells.push(Cell {
                    label: label.to_string(),
                    d0: col,
                    seed,
                    successes,
                    episodes,
                    overruns,
                });
            }
        }
    }
    Ok(cells)
}
