//! The rolling latency window that measures the delay `d`.

use crate::clock::Nanos;

/// Rolling mean of call latencies; `d = max(1, round(mean / T_ctrl))`, clamped to `d_max`.
///
/// The first `warmup` calls are not recorded, so a cold first call (page faults, lazy
/// initialisation, JIT) cannot poison `d`. Fixed capacity: pushing never allocates.
///
/// ```
/// use pir2_runtime::window::LatencyWindow;
/// let mut w = LatencyWindow::new(4, 1, 20_000_000, 5); // W = 4, 1 warm-up call, 50 Hz, d_max 5
/// w.push(900_000_000); // cold call: ignored
/// for _ in 0..4 { w.push(25_000_000); } // 25 ms calls at 20 ms ticks
/// assert_eq!(w.delay(), 1);
/// for _ in 0..4 { w.push(45_000_000); }
/// assert_eq!(w.delay(), 2);
/// ```
#[derive(Debug, Clone)]
pub struct LatencyWindow {
    buf: Vec<Nanos>,
    len: usize,
    head: usize,
    sum: u128,
    warmup_left: usize,
    period: Nanos,
    d_max: usize,
    d_min: usize,
    initial: usize,
}

impl LatencyWindow {
    /// Window of `w` calls (`w ≥ 1`), skipping the first `warmup` pushes, control period
    /// `period` ns, clamp at `d_max`.
    pub fn new(w: usize, warmup: usize, period: Nanos, d_max: usize) -> Self {
        let w = w.max(1);
        Self {
            buf: vec![0; w],
            len: 0,
            head: 0,
            sum: 0,
            warmup_left: warmup,
            period: period.max(1),
            d_max: d_max.max(1),
            d_min: 1,
            initial: 1,
        }
    }

    /// The delay reported before any latency has been recorded (default 1).
    pub fn with_initial_delay(mut self, d: usize) -> Self {
        self.initial = d.clamp(self.d_min, self.d_max);
        self
    }

    /// Record one call latency.
    pub fn push(&mut self, latency: Nanos) {
        if self.warmup_left > 0 {
            self.warmup_left -= 1;
            return;
        }
        let w = self.buf.len();
        if self.len == w {
            self.sum -= self.buf[self.head] as u128;
        } else {
            self.len += 1;
        }
        self.buf[self.head] = latency;
        self.sum += latency as u128;
        self.head = (self.head + 1) % w;
    }

    /// Mean latency over the window (ns), if anything was recorded.
    pub fn mean(&self) -> Option<f64> {
        (self.len > 0).then(|| self.sum as f64 / self.len as f64)
    }

    /// Number of recorded latencies.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when nothing is recorded yet.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// `d = max(1, round(mean / T_ctrl))`, clamped to `d_max`.
    pub fn delay(&self) -> usize {
        match self.mean() {
            None => self.initial,
            Some(m) => ((m / self.period as f64).round() as usize).clamp(self.d_min, self.d_max),
        }
    }
}
