//! Injectable clocks: the runtime never reads `Instant::now()` directly.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Nanoseconds since the clock's epoch.
pub type Nanos = u64;

/// A monotonic clock. The real-time driver uses [`SystemClock`]; tests step a [`MockClock`].
pub trait Clock: Send + Sync + std::fmt::Debug {
    /// Now, in nanoseconds since the clock's epoch.
    fn now(&self) -> Nanos;
    /// Sleep until `deadline` (no-op if it already passed).
    fn sleep_until(&self, deadline: Nanos);
}

/// Wall clock based on [`Instant`], epoch = construction time.
#[derive(Debug, Clone)]
pub struct SystemClock {
    epoch: Instant,
}

impl Default for SystemClock {
    fn default() -> Self {
        Self::new()
    }
}

impl SystemClock {
    /// A clock whose epoch is now.
    pub fn new() -> Self {
        Self {
            epoch: Instant::now(),
        }
    }
}

impl Clock for SystemClock {
    fn now(&self) -> Nanos {
        self.epoch.elapsed().as_nanos() as Nanos
    }
    fn sleep_until(&self, deadline: Nanos) {
        // Coarse sleep, then spin the last ~200 µs: the kernel's sleep granularity
        // would otherwise add tens of µs of jitter to every tick.
        const SPIN: Nanos = 200_000;
        loop {
            let now = self.now();
            if now >= deadline {
                return;
            }
            let left = deadline - now;
            if left > SPIN {
                std::thread::sleep(Duration::from_nanos(left - SPIN));
            } else {
                std::hint::spin_loop();
                if left > 20_000 {
                    std::thread::yield_now();
                }
            }
        }
    }
}

/// A clock that only moves when told to. Cloning shares the same time.
#[derive(Debug, Clone, Default)]
pub struct MockClock {
    now: Arc<AtomicU64>,
}

impl MockClock {
    /// A mock clock at time 0.
    pub fn new() -> Self {
        Self::default()
    }
    /// Advance by `dt` nanoseconds.
    pub fn advance(&self, dt: Nanos) {
        self.now.fetch_add(dt, Ordering::SeqCst);
    }
    /// Set the absolute time.
    pub fn set(&self, t: Nanos) {
        self.now.store(t, Ordering::SeqCst);
    }
}

impl Clock for MockClock {
    fn now(&self) -> Nanos {
        self.now.load(Ordering::SeqCst)
    }
    /// A mock sleep jumps the clock forward to the deadline.
    fn sleep_until(&self, deadline: Nanos) {
        self.now.fetch_max(deadline, Ordering::SeqCst);
    }
}
