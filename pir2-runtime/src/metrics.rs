//! Run metrics: per-call latency, `d`, `d_vis`, overruns, tick jitter, swaps; a JSON trace.

use serde::{Deserialize, Serialize};

use crate::clock::Nanos;

/// A fixed-size log-bucketed histogram of durations (ns): recording never allocates.
/// Buckets are 1/16-octave wide from 1 µs to ~67 s; percentiles are bucket midpoints
/// (relative resolution ≈ 4%).
#[derive(Debug, Clone)]
pub struct Histogram {
    counts: Box<[u64; Self::BUCKETS]>,
    total: u64,
    sum: u128,
    max: Nanos,
}

impl Default for Histogram {
    fn default() -> Self {
        Self {
            counts: Box::new([0; Self::BUCKETS]),
            total: 0,
            sum: 0,
            max: 0,
        }
    }
}

impl Histogram {
    const SUB: usize = 16;
    const BUCKETS: usize = 26 * Self::SUB + 1;

    fn bucket(v: Nanos) -> usize {
        if v < 1000 {
            return 0;
        }
        let x = (v as f64 / 1000.0).log2() * Self::SUB as f64;
        (x as usize + 1).min(Self::BUCKETS - 1)
    }

    fn value(b: usize) -> Nanos {
        if b == 0 {
            return 500;
        }
        (1000.0 * 2f64.powf((b as f64 - 0.5) / Self::SUB as f64)) as Nanos
    }

    /// Record one value.
    pub fn record(&mut self, v: Nanos) {
        self.counts[Self::bucket(v)] += 1;
        self.total += 1;
        self.sum += v as u128;
        self.max = self.max.max(v);
    }

    /// Number of values.
    pub fn count(&self) -> u64 {
        self.total
    }

    /// Mean (ns).
    pub fn mean(&self) -> f64 {
        if self.total == 0 {
            0.0
        } else {
            self.sum as f64 / self.total as f64
        }
    }

    /// Largest value (exact).
    pub fn max(&self) -> Nanos {
        self.max
    }

    /// Percentile `q ∈ [0, 100]` (bucket midpoint).
    pub fn percentile(&self, q: f64) -> Nanos {
        if self.total == 0 {
            return 0;
        }
        let rank = ((q / 100.0) * self.total as f64).ceil().max(1.0) as u64;
        let mut acc = 0;
        for (b, &c) in self.counts.iter().enumerate() {
            acc += c;
            if acc >= rank {
                return Self::value(b).min(self.max);
            }
        }
        self.max
    }

    /// p50/p90/p99/max summary.
    pub fn summary(&self) -> Percentiles {
        Percentiles {
            count: self.total,
            mean: self.mean(),
            p50: self.percentile(50.0),
            p90: self.percentile(90.0),
            p99: self.percentile(99.0),
            max: self.max,
        }
    }
}

/// A percentile summary (all ns).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Percentiles {
    /// Number of samples.
    pub count: u64,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub p50: Nanos,
    /// 90th percentile.
    pub p90: Nanos,
    /// 99th percentile.
    pub p99: Nanos,
    /// Maximum.
    pub max: Nanos,
}

/// One action-head call, as recorded by the worker.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct CallRecord {
    /// Tick of the snapshot.
    pub tick: u64,
    /// Measured (or injected) latency, ns.
    pub latency: Nanos,
    /// Delay `d` used for the call.
    pub d: usize,
    /// Age of the slow features in ticks.
    pub d_vis: usize,
    /// Ticks elapsed between the snapshot and the swap (filled in at the swap).
    pub elapsed: usize,
}

/// Everything a run records. Control-side counters never allocate; the per-call trace is
/// appended by the worker.
#[derive(Debug, Clone, Default)]
pub struct RunMetrics {
    /// Control ticks run.
    pub ticks: u64,
    /// Ticks whose action was a clean estimate `x̂` (no clean slot was available).
    pub overruns: u64,
    /// Ticks that held the last action (sync mode while waiting, or nothing at all available).
    pub holds: u64,
    /// Chunk swaps.
    pub swaps: u64,
    /// Ticks that started more than one period late. The missed deadlines are skipped, not
    /// caught up: the late tick sends one action and the schedule restarts from it.
    pub late_ticks: u64,
    /// Tick jitter: lateness of each tick's start past its deadline.
    pub tick_jitter: Histogram,
    /// Time spent inside the control step (runtime overhead, excludes the model).
    pub tick_overhead: Histogram,
    /// Call latencies.
    pub call_latency: Histogram,
    /// Per-call trace.
    pub calls: Vec<CallRecord>,
    /// Safety stops and other events, in order.
    pub events: Vec<String>,
}

/// Serializable summary + trace of a run (what `pir2 plot` reads).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RunTrace {
    /// Control period, ns.
    pub period: Nanos,
    /// Ticks run.
    pub ticks: u64,
    /// Overruns.
    pub overruns: u64,
    /// Holds.
    pub holds: u64,
    /// Swaps.
    pub swaps: u64,
    /// Ticks more than one period late (missed deadlines skipped, never caught up).
    #[serde(default)]
    pub late_ticks: u64,
    /// Tick jitter percentiles.
    pub tick_jitter: Percentiles,
    /// Control-step overhead percentiles.
    pub tick_overhead: Percentiles,
    /// Call latency percentiles.
    pub call_latency: Percentiles,
    /// Per-call records.
    pub calls: Vec<CallRecord>,
    /// Events.
    pub events: Vec<String>,
}

impl RunMetrics {
    /// Summarise into a serializable trace.
    pub fn trace(&self, period: Nanos) -> RunTrace {
        RunTrace {
            period,
            ticks: self.ticks,
            overruns: self.overruns,
            holds: self.holds,
            swaps: self.swaps,
            late_ticks: self.late_ticks,
            tick_jitter: self.tick_jitter.summary(),
            tick_overhead: self.tick_overhead.summary(),
            call_latency: self.call_latency.summary(),
            calls: self.calls.clone(),
            events: self.events.clone(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_percentiles_are_close() {
        let mut h = Histogram::default();
        for i in 1..=1000u64 {
            h.record(i * 10_000); // 10 µs .. 10 ms
        }
        let p50 = h.percentile(50.0) as f64;
        assert!((p50 / 5_000_000.0 - 1.0).abs() < 0.05, "{p50}");
        let p99 = h.percentile(99.0) as f64;
        assert!((p99 / 9_900_000.0 - 1.0).abs() < 0.05, "{p99}");
        assert_eq!(h.max(), 10_000_000);
    }
}
