//! Deployment studies through the lock-step runtime: modes × unit delays × seeds.

use serde::{Deserialize, Serialize};

use pir2_runtime::{
    ActionHead, OutputMap, Environment, HeadSpec, LatencyWindow, LockstepDriver, LockstepTiming, Mode,
    VelocityModel,
};
use pir2_schedule::Rng;

use crate::plot::Series;

/// One cell of a study: a row (policy + mode) at one `d0` and seed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Cell {
    /// Row label.
    pub label: String,
    /// Unit delay.
    pub d0: usize,
    /// Training/evaluation seed.
    pub seed: u64,
    /// Episodes that succeeded.
    pub successes: usize,
    /// Episodes run.
    pub episodes: usize,
    /// Overrun ticks over all episodes.
    pub overruns: u64,
}

impl Cell {
    /// Success rate.
    pub fn rate(&self) -> f64 {
        self.successes as f64 / self.episodes.max(1) as f64
    }
}

/// Run `episodes` episodes of one cell in parallel on `threads` threads. Every episode
/// gets its own environment, head and seeds derived from `(seed, episode)`, so the result
/// does not depend on the thread count.
#[allow(clippy::too_many_arguments)]
pub fn eval_cell<E, M, FE, FM>(
    make_env: &FE,
    make_model: &FM,
    spec: HeadSpec,
    mode: &Mode,
    timing: LockstepTiming,
    output: &OutputMap,
    episodes: usize,
    seed: u64,
    threads: usize,
    progress: &(dyn Fn() + Sync),
) -> pir2_runtime::Result<(usize, u64)>
where
    E: Environment,
    M: VelocityModel,
    FE: Fn() -> E + Sync,
    FM: Fn() -> M + Sync,
{
    let threads = threads.clamp(1, episodes.max(1));
    let results: Vec<pir2_runtime::Result<(usize, u64)>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..threads)
            .map(|w| {
                s.spawn(move || -> pir2_runtime::Result<(usize, u64)> {
                    let mut env = make_env();
                    let (mut ok, mut overruns) = (0, 0);
                    let mut ep = w;
                    while ep < episodes {
                        let ep_seed = Rng::derive(seed, ep as u64).next_u64();
                        let window = LatencyWindow::new(20, 0, spec.period, spec.d_max);
                        let mut head = ActionHead::new(
                            make_model(),
                            spec,
                            mode.head_mode(10),
                            window,
                            ep_seed ^ 0xA5A5,
                        )?;
                        let mut drv = LockstepDriver::new(&head).with_output(output.clone());
                        let r =
                            drv.run_episode(&mut env, &mut head, mode, timing, ep_seed, |_, _| {})?;
                        ok += r.success as usize;
                        overruns += r.metrics.overruns;
                        progress();
                        ep += threads;
                    }
                    Ok((ok, overruns))
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().expect("evaluation thread panicked"))
            .collect()
    });
    let mut total = (0, 0);
    for r in results {
        let (a, b) = r?;
        total.0 += a;
        total.1 += b;
    }
    Ok(total)
}

/// Mean and (population) standard deviation.
pub fn mean_std(xs: &[f64]) -> (f64, f64) {
    if xs.is_empty() {
        return (0.0, 0.0);
    }
    let m = xs.iter().sum::<f64>() / xs.len() as f64;
    let v = xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / xs.len() as f64;
    (m, v.sqrt())
}

/// Aggregate cells into one series per label: `(d0, mean, std)` over seeds.
pub fn to_series(cells: &[Cell], labels: &[String], d0s: &[usize]) -> Vec<Series> {
    labels
        .iter()
        .map(|l| Series {
            label: l.clone(),
            points: d0s
                .iter()
                .filter_map(|&d0| {
                    let rates: Vec<f64> = cells
                        .iter()
                        .filter(|c| &c.label == l && c.d0 == d0)
                        .map(Cell::rate)
                        .collect();
                    (!rates.is_empty()).then(|| {
                        let (m, s) = mean_std(&rates);
                        (d0 as f64, m, s)
                    })
                })
                .collect(),
        })
        .filter(|s| !s.points.is_empty())
        .collect()
}

/// A Markdown table: one row per label, one column per `d0`, `mean ± std`.
pub fn table(cells: &[Cell], labels: &[String], d0s: &[usize]) -> String {
    let mut out = String::from("| policy / mode |");
    for d0 in d0s {
        out += &format!(" d0={d0} |");
    }
    out += "\n|---|";
    for _ in d0s {
        out += "---|";
    }
    out += "\n";
    for s in to_series(cells, labels, d0s) {
        out += &format!("| {} |", s.label);
        for &d0 in d0s {
            match s.points.iter().find(|p| p.0 as usize == d0) {
                Some(p) => out += &format!(" {:.2} ± {:.2} |", p.1, p.2),
                None => out += " – |",
            }
        }
        out += "\n";
    }
    out
}
