//! The control side of the state machine: which action goes out at each tick.
//!
//! Per tick the driver (real-time or lock-step) reads fresh proprioception, publishes it,
//! swaps in a new chunk if one is ready ([`ControlState::deliver`]), sends one action
//! ([`ControlState::action`]) and advances. Nothing here allocates or blocks.

use serde::{Deserialize, Serialize};

use crate::chunk::Chunk;
use crate::error::{Error, Result};
use crate::metrics::RunMetrics;

/// Calls recorded in a run's trace (reserved up front; later calls are only counted).
pub const TRACE_CAPACITY: usize = 1 << 16;

/// When the action head is called.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum CallPolicy {
    /// A new call starts as soon as the previous one delivered (all asynchronous modes).
    Async,
    /// Synchronous flow: the robot holds while the call runs, then executes `h` actions of
    /// the new chunk from its first slot; only then is the next call made.
    Sync {
        /// Execution horizon `h`.
        h: usize,
    },
}

/// Affine map from model action space to robot commands: `u = c(x)·scale + offset`, where
/// `c` clips `x` to `[-1, 1]` on the dimensions marked in `clip` (a min/max-normalised action,
/// as GR00T decodes it) and is the identity elsewhere.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct OutputMap {
    /// Per-dimension scale (empty = 1).
    pub scale: Vec<f32>,
    /// Per-dimension offset (empty = 0).
    pub offset: Vec<f32>,
    /// Per-dimension clip to `[-1, 1]` before the scale (empty = none).
    #[serde(default)]
    pub clip: Vec<bool>,
}

impl OutputMap {
    /// Map one action `x` into `out`.
    pub fn apply(&self, x: &[f32], out: &mut [f32]) {
        for (j, (o, &v)) in out.iter_mut().zip(x).enumerate() {
            let v = if self.clip.get(j).copied().unwrap_or(false) {
                v.clamp(-1.0, 1.0)
            } else {
                v
            };
            let s = self.scale.get(j).copied().unwrap_or(1.0);
            let b = self.offset.get(j).copied().unwrap_or(0.0);
            *o = v * s + b;
        }
    }
}

/// Configuration of the control side.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ControlConfig {
    /// Chunk length `H`.
    pub horizon: usize,
    /// Action dimension `A`.
    pub action_dim: usize,
    /// When calls are made.
    pub policy: CallPolicy,
    /// ACT temporal ensembling with weights `exp(−m·i)` (oldest first), for naive async.
    pub ensemble: Option<f32>,
    /// Map to robot commands.
    pub output: OutputMap,
}

/// Control-loop state (see the module docs).
#[derive(Debug)]
pub struct ControlState {
    cfg: ControlConfig,
    tick: u64,
    current: Chunk,
    has_current: bool,
    ring: Vec<Chunk>,
    ring_len: usize,
    ring_head: usize,
    weights: Vec<f32>,
    last: Vec<f32>,
    out: Vec<f32>,
    in_flight: bool,
    executed_since_swap: usize,
    /// Metrics of the run.
    pub metrics: RunMetrics,
}

impl ControlState {
    /// New control state; validates the output map's sizes.
    pub fn new(cfg: ControlConfig) -> Result<Self> {
        let (h, a) = (cfg.horizon, cfg.action_dim);
        if h == 0 || a == 0 {
            return Err(Error::Config(format!(
                "horizon ({h}) and action_dim ({a}) must be positive"
            )));
        }
        for (name, v) in [
            ("output.scale", &cfg.output.scale),
            ("output.offset", &cfg.output.offset),
        ] {
            if !v.is_empty() && v.len() != a {
                return Err(Error::Config(format!(
                    "{name} has {} entries, expected action_dim = {a}",
                    v.len()
                )));
            }
        }
        let clip = cfg.output.clip.len();
        if clip != 0 && clip != a {
            return Err(Error::Config(format!(
                "output.clip has {clip} entries, expected action_dim = {a}"
            )));
        }
        if let CallPolicy::Sync { h: he } = cfg.policy {
            if he == 0 || he > h {
                return Err(Error::Config(format!(
                    "sync execution horizon h = {he} must be in 1..={h}"
                )));
            }
        }
        let ring_cap = if cfg.ensemble.is_some() { h } else { 0 };
        Ok(Self {
            tick: 0,
            current: Chunk::new(h, a),
            has_current: false,
            ring: (0..ring_cap).map(|_| Chunk::new(h, a)).collect(),
            ring_len: 0,
            ring_head: 0,
            weights: vec![0.0; ring_cap.max(1)],
            last: vec![0.0; a],
            out: vec![0.0; a],
            in_flight: false,
            executed_since_swap: 0,
            metrics: RunMetrics {
                calls: Vec::with_capacity(TRACE_CAPACITY),
                ..RunMetrics::default()
            },
            cfg,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &ControlConfig {
        &self.cfg
    }

    /// The current tick (the tick whose action is sent next).
    pub fn tick(&self) -> u64 {
        self.tick
    }

    /// Set the last-action memory (what a hold sends), e.g. the robot's current targets.
    pub fn set_hold(&mut self, action: &[f32]) {
        self.last.copy_from_slice(action);
    }

    /// Should a new call start now? (The driver also tracks whether one is in flight.)
    pub fn wants_call(&self) -> bool {
        if self.in_flight {
            return false;
        }
        match self.cfg.policy {
            CallPolicy::Async => true,
            CallPolicy::Sync { h } => !self.has_current || self.executed_since_swap >= h,
        }
    }

    /// Mark that a call has started (a snapshot was taken at the current tick).
    pub fn call_started(&mut self) {
        self.in_flight = true;
    }

    /// Swap in a delivered chunk. `chunk` receives the previous chunk's storage (no
    /// allocation). The index into the new chunk is the number of ticks elapsed since its
    /// snapshot (async), or its first slot (sync: the robot held meanwhile).
    pub fn deliver(&mut self, chunk: &mut Chunk) {
        self.in_flight = false;
        let elapsed = self.tick.saturating_sub(chunk.snapshot_tick) as usize;
        chunk.call.elapsed = elapsed;
        // The trace has a fixed capacity reserved up front: the control tick never allocates.
        if self.metrics.calls.len() < self.metrics.calls.capacity() {
            self.metrics.calls.push(chunk.call);
        }
        self.metrics.call_latency.record(chunk.call.latency);
        if let CallPolicy::Sync { .. } = self.cfg.policy {
            chunk.base = self.tick;
        }
        self.metrics.swaps += 1;
        self.executed_since_swap = 0;
        if self.cfg.ensemble.is_some() {
            let cap = self.ring.len();
            let slot = (self.ring_head + self.ring_len) % cap;
            if self.ring_len == cap {
                self.ring_head = (self.ring_head + 1) % cap;
            } else {
                self.ring_len += 1;
            }
            self.ring[slot].copy_from(chunk);
        }
        std::mem::swap(&mut self.current, chunk);
        self.has_current = true;
    }

    /// The command for the current tick (already mapped through the output map), then
    /// advance to the next tick.
    pub fn action(&mut self) -> &[f32] {
        let t = self.tick;
        self.metrics.ticks += 1;
        let held = self.in_flight && matches!(self.cfg.policy, CallPolicy::Sync { .. });
        let mut produced = false;
        if !held {
            if let Some(m) = self.cfg.ensemble {
                produced = self.ensemble_at(t, m);
            } else if self.has_current {
                if let Some((v, clean)) = self.current.action_at(t) {
                    self.last.copy_from_slice(v);
                    if !clean {
                        self.metrics.overruns += 1;
                    }
                    produced = true;
                } else {
                    // Past the end of the chunk: nothing left to execute.
                    self.metrics.overruns += 1;
                }
            }
        }
        if !produced {
            self.metrics.holds += 1;
        } else {
            self.executed_since_swap += 1;
        }
        self.tick += 1;
        self.cfg.output.apply(&self.last, &mut self.out);
        &self.out
    }

    /// The last action in model space (what a hold repeats).
    pub fn last_action(&self) -> &[f32] {
        &self.last
    }

    fn ensemble_at(&mut self, t: u64, m: f32) -> bool {
        let cap = self.ring.len();
        let mut n = 0;
        for i in 0..self.ring_len {
            let c = &self.ring[(self.ring_head + i) % cap];
            if c.index_of(t).is_some() {
                n += 1;
            }
        }
        if n == 0 {
            return false;
        }
        pir2_schedule::baselines::ensemble_weights(m, &mut self.weights[..n]);
        self.last.fill(0.0);
        let mut k = 0;
        for i in 0..self.ring_len {
            let c = &self.ring[(self.ring_head + i) % cap];
            if let Some((v, _)) = c.action_at(t) {
                let w = self.weights[k];
                for (l, x) in self.last.iter_mut().zip(v) {
                    *l += w * x;
                }
                k += 1;
            }
        }
        true
    }
}
