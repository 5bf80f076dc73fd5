//! A study's results: one [`Cell`] per row × seed × column, aggregated over seeds into
//! plot series and a Markdown table, and a study's `result.json` plotted ([`plot_result`]).

use std::path::Path;

use anyhow::{anyhow, Result};
use serde::{Deserialize, Serialize};

use crate::plot::{plot_series, Series};

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

/// Plot a study's `result.json` (labels, cells, columns; results written before the columns
/// were recorded give them as `config.d0s`).
pub fn plot_result(v: &serde_json::Value, out: &Path) -> Result<()> {
    #[derive(Deserialize)]
    struct StudyFile {
        labels: Vec<String>,
        cells: Vec<Cell>,
        #[serde(default)]
        key: Option<String>,
        #[serde(default)]
        columns: Option<Vec<usize>>,
        #[serde(default)]
        config: serde_json::Value,
    }
    let r: StudyFile = serde_json::from_value(v.clone())?;
    let columns = match r.columns {
        Some(c) => c,
        None => serde_json::from_value(r.config["d0s"].clone())
            .map_err(|e| anyhow!("the result names no columns (nor config.d0s): {e}"))?,
    };
    let series = to_series(&r.cells, &r.labels, &columns);
    let (title, x) = match r.key.as_deref() {
        Some("h") => (
            "success vs execution horizon",
            "execution horizon h (ticks)",
        ),
        _ => ("success vs unit delay", "unit delay d0 (ticks)"),
    };
    plot_series(out, title, x, "success rate", &series)
}

/// A Markdown table: one row per label, one column per `d0`, `mean ± std`.
pub fn table(cells: &[Cell], labels: &[String], d0s: &[usize]) -> String {
    table_keyed(cells, labels, d0s, "d0")
}

/// [`table`] with the columns named `key=` (`d0`, `h`).
pub fn table_keyed(cells: &[Cell], labels: &[String], columns: &[usize], key: &str) -> String {
    let mut out = header("policy / mode", columns, key);
    for s in to_series(cells, labels, columns) {
        out += &format!("| {} |", s.label);
        for &c in columns {
            match s.points.iter().find(|p| p.0 as usize == c) {
                Some(p) => out += &format!(" {:.2} ± {:.2} |", p.1, p.2),
                None => out += " – |",
            }
        }
        out += "\n";
    }
    out
}

/// A Markdown table of each seed's success rate: one row per label, one column per value of
/// `columns` (named `key=`), holding the rates of `seeds` in that order as `a / b / c`, `–`
/// for a seed without the cell.
pub fn per_seed_table(
    cells: &[Cell],
    labels: &[String],
    columns: &[usize],
    key: &str,
    seeds: &[u64],
) -> String {
    let names: Vec<String> = seeds.iter().map(u64::to_string).collect();
    let mut out = header(
        &format!("policy / mode (seeds {})", names.join(" / ")),
        columns,
        key,
    );
    for l in labels {
        if !cells.iter().any(|c| &c.label == l) {
            continue;
        }
        out += &format!("| {l} |");
        for &col in columns {
            let rates: Vec<String> = seeds
                .iter()
                .map(|&s| {
                    cells
                        .iter()
                        .find(|c| &c.label == l && c.d0 == col && c.seed == s)
                        .map_or_else(|| "–".to_string(), |c| format!("{:.2}", c.rate()))
                })
                .collect();
            out += &format!(" {} |", rates.join(" / "));
        }
        out += "\n";
    }
    out
}

/// The header and separator lines of a Markdown table whose first column is `first` and
/// whose other columns are named `key=<value>`.
fn header(first: &str, columns: &[usize], key: &str) -> String {
    let mut out = format!("| {first} |");
    for c in columns {
        out += &format!(" {key}={c} |");
    }
    out += "\n|---|";
    for _ in columns {
        out += "---|";
    }
    out += "\n";
    out
}
