//! Chunks handed from the action head to the control loop.

use crate::metrics::CallRecord;

/// A chunk as the control loop executes it: absolute tick of slot 0, the values, the
/// clean estimates `x̂`, and which slots are clean (`τ = 1`).
#[derive(Debug, Clone, PartialEq)]
pub struct Chunk {
    /// Absolute control tick of slot 0.
    pub base: u64,
    /// Chunk length `H`.
    pub horizon: usize,
    /// Action dimension `A`.
    pub action_dim: usize,
    /// Values `x`, `[H, A]`.
    pub x: Vec<f32>,
    /// Clean estimates `x̂`, `[H, A]`.
    pub xhat: Vec<f32>,
    /// `clean[p]` ⇔ `τ_p = 1`.
    pub clean: Vec<bool>,
    /// The reference of relative actions, `[A]`: per action dimension, the value of the
    /// snapshot's newest fast observation the action is relative to (0 for an absolute
    /// dimension; see [`OutputMap`](crate::OutputMap)). Set by the action head.
    pub reference: Vec<f32>,
    /// Tick of the snapshot the chunk was computed from.
    pub snapshot_tick: u64,
    /// The call that produced it.
    pub call: CallRecord,
}

impl Chunk {
    /// An empty chunk (nothing clean) with preallocated storage.
    pub fn new(horizon: usize, action_dim: usize) -> Self {
        Self {
            base: 0,
            horizon,
            action_dim,
            x: vec![0.0; horizon * action_dim],
            xhat: vec![0.0; horizon * action_dim],
            clean: vec![false; horizon],
            reference: vec![0.0; action_dim],
            snapshot_tick: 0,
            call: CallRecord::default(),
        }
    }

    /// Slot index of tick `t`, if the chunk covers it.
    pub fn index_of(&self, t: u64) -> Option<usize> {
        if t < self.base {
            return None;
        }
        let i = (t - self.base) as usize;
        (i < self.horizon).then_some(i)
    }

    /// The action to execute at tick `t`: `(values, was_clean)`. A slot with `τ < 1` gives
    /// its clean estimate `x̂` (never a noisy value).
    pub fn action_at(&self, t: u64) -> Option<(&[f32], bool)> {
        let i = self.index_of(t)?;
        let a = self.action_dim;
        if self.clean[i] {
            Some((&self.x[i * a..(i + 1) * a], true))
        } else {
            Some((&self.xhat[i * a..(i + 1) * a], false))
        }
    }

    /// Copy another chunk's contents (same sizes) without allocating.
    pub fn copy_from(&mut self, other: &Chunk) {
        self.base = other.base;
        self.x.copy_from_slice(&other.x);
        self.xhat.copy_from_slice(&other.xhat);
        self.clean.copy_from_slice(&other.clean);
        self.reference.copy_from_slice(&other.reference);
        self.snapshot_tick = other.snapshot_tick;
        self.call = other.call;
    }
}
