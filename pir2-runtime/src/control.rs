//! The control side of the state machine: which action goes out at each tick.
//!
//! One file on purpose: the control state's swap, overrun, hold and ensembling rules act on the
//! same buffers, tick by tick.
//!
//! Per tick the driver (real-time or lock-step) reads fresh proprioception, publishes it,
//! swaps in a new chunk if one is ready ([`ControlState::deliver`]), sends one action
//! ([`ControlState::action`]) and advances. Nothing here allocates or blocks.

use serde::{Deserialize, Serialize};

use crate::chunk::Chunk;
use crate::error::{Error, Result};
use crate::metrics::RunMetrics;
use crate::pose::{self, PoseFormat};

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

/// Map from model action space to robot commands. For action dimension `j` at slot `i` of
/// its chunk: `u_j = c(x_j)·scale[i, j] + offset[i, j] + r_j`, where
/// - `c` clips `x` to `[-1, 1]` on the dimensions marked in `clip` (a min/max-normalised
///   action, as GR00T decodes it) and is the identity elsewhere;
/// - `scale`/`offset` hold either one value per dimension (`[A]`, the same for every slot)
///   or one per slot and dimension (`[H, A]`, slot-major: per-position statistics, as GR00T's
///   relative-action statistics are);
/// - `r_j` is the chunk's reference for a relative dimension (`reference[j] = Some(k)`: the
///   action is relative to value `k` of the newest fast observation at the chunk's
///   snapshot, see [`Chunk::reference`]) and 0 for an absolute one.
///
/// A map with per-slot statistics or relative dimensions ([`OutputMap::per_slot`]) is
/// decoded per chunk before temporal ensembling, and the action head rebases the actions it
/// carries from call to call onto the new reference and slot ([`OutputMap::rebase`]).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct OutputMap {
    /// Scale, `[A]` or `[H, A]` (empty = 1).
    pub scale: Vec<f32>,
    /// Offset, `[A]` or `[H, A]` (empty = 0).
    pub offset: Vec<f32>,
    /// Per-dimension clip to `[-1, 1]` before the scale (empty = none).
    #[serde(default)]
    pub clip: Vec<bool>,
    /// Per dimension, the fast-observation value the action is relative to (`None` =
    /// absolute; empty = every dimension absolute).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub reference: Vec<Option<usize>>,
    /// Relative end-effector poses among the relative dimensions: each group's dimensions
    /// `first .. first + width` are one pose relative to the reference pose (its dimensions'
    /// `reference` entries), decoded as `T_ref·T_rel` (see [`crate::pose`]) after the
    /// per-dimension scale and offset, instead of adding the reference per dimension.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub poses: Vec<PoseGroup>,
}

/// A relative end-effector pose among the action dimensions (see [`OutputMap::poses`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct PoseGroup {
    /// Its first action dimension.
    pub first: usize,
    /// Its layout (and width).
    pub format: PoseFormat,
}

impl PoseGroup {
    /// The action dimensions of the pose.
    pub fn dims(&self) -> std::ops::Range<usize> {
        self.first..self.first + self.format.width()
    }
}

impl OutputMap {
    /// Map one action `x` into `out` with the slot-0 statistics and no reference (the map
    /// of an absolute, per-dimension output; see [`decode`](Self::decode) for the general
    /// one).
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

    /// Check the sizes against `H` and `A`; the error names the field.
    pub fn validate(&self, horizon: usize, action_dim: usize) -> Result<()> {
        let a = action_dim;
        for (name, v) in [
            ("output.scale", &self.scale),
            ("output.offset", &self.offset),
        ] {
            if !v.is_empty() && v.len() != a && v.len() != horizon * a {
                return Err(Error::Config(format!(
                    "{name} has {} entries, expected action_dim = {a} or horizon × action_dim = {}",
                    v.len(),
                    horizon * a
                )));
            }
        }
        for (name, n) in [
            ("output.clip", self.clip.len()),
            ("output.reference", self.reference.len()),
        ] {
            if n != 0 && n != a {
                return Err(Error::Config(format!(
                    "{name} has {n} entries, expected action_dim = {a}"
                )));
            }
        }
        for (i, g) in self.poses.iter().enumerate() {
            let dims = g.dims();
            if dims.end > a {
                return Err(Error::Config(format!(
                    "output.poses[{i}] covers dimensions {dims:?}, the action has {a}"
                )));
            }
            if let Some(j) = dims.clone().find(|&j| !self.is_relative(j)) {
                return Err(Error::Config(format!(
                    "output.poses[{i}]: dimension {j} has no reference (a pose is relative)"
                )));
            }
            if let Some(o) = self.poses[..i]
                .iter()
                .find(|o| o.first < dims.end && dims.start < o.dims().end)
            {
                return Err(Error::Config(format!(
                    "output.poses[{i}] ({dims:?}) overlaps {:?}",
                    o.dims()
                )));
            }
        }
        Ok(())
    }

    /// The pose group holding dimension `j`, if any.
    fn pose_of(&self, j: usize) -> Option<&PoseGroup> {
        self.poses.iter().find(|g| g.dims().contains(&j))
    }

    /// Does decoding depend on the slot or on the chunk's reference (per-slot statistics or
    /// a relative dimension)? Such a map is decoded chunk by chunk, and carried actions are
    /// rebased between calls.
    pub fn per_slot(&self, action_dim: usize) -> bool {
        self.scale.len() > action_dim
            || self.offset.len() > action_dim
            || self.reference.iter().any(Option::is_some)
    }

    /// Is dimension `j` relative?
    pub fn is_relative(&self, j: usize) -> bool {
        self.reference.get(j).copied().flatten().is_some()
    }

    fn stat(v: &[f32], slot: usize, j: usize, a: usize, default: f32) -> f32 {
        if v.len() > a {
            v[slot * a + j]
        } else {
            v.get(j).copied().unwrap_or(default)
        }
    }

    /// The scale and offset of dimension `j` at `slot`.
    fn affine(&self, slot: usize, j: usize, a: usize) -> (f32, f32) {
        (
            Self::stat(&self.scale, slot, j, a, 1.0),
            Self::stat(&self.offset, slot, j, a, 0.0),
        )
    }

    /// The reference of a chunk whose snapshot's newest fast observation is `obs`: per
    /// action dimension, the referenced value (0 for an absolute dimension). `obs` must be
    /// longer than every index in `reference` (checked by the action head).
    pub fn fill_reference(&self, obs: &[f32], out: &mut [f32]) {
        for (j, r) in out.iter_mut().enumerate() {
            *r = match self.reference.get(j).copied().flatten() {
                Some(k) => obs[k],
                None => 0.0,
            };
        }
    }

    /// Decode one action `x` at `slot` of a chunk with reference `reference` (`[A]`, see
    /// [`fill_reference`](Self::fill_reference)) into the command `out`.
    pub fn decode(&self, x: &[f32], slot: usize, reference: &[f32], out: &mut [f32]) {
        let a = x.len();
        for (j, (o, &v)) in out.iter_mut().zip(x).enumerate() {
            let v = if self.clip.get(j).copied().unwrap_or(false) {
                v.clamp(-1.0, 1.0)
            } else {
                v
            };
            let (s, b) = self.affine(slot, j, a);
            let u = v * s + b;
            *o = if self.is_relative(j) && self.pose_of(j).is_none() {
                u + reference[j]
            } else {
                u
            };
        }
        for g in &self.poses {
            let r = g.dims();
            let mut rel = [0f32; 9];
            rel[..r.len()].copy_from_slice(&out[r.clone()]);
            pose::absolute(
                g.format,
                &reference[r.clone()],
                &rel[..r.len()],
                &mut out[r],
            );
        }
    }

    /// Rebase one carried action: `z` was at slot `from_slot` of a chunk with reference
    /// `from_ref`; `out` receives the model-space value at slot `to_slot` relative to
    /// `to_ref` that decodes to the same command, `z′ = (u − r′ − offset′)/scale′` with `u`
    /// the command `z` decoded to. A dimension whose statistics and reference do not change
    /// is copied bit for bit; so is one whose new scale is 0 (a degenerate statistic: every
    /// value decodes to the same command). A command outside the new slot's clip range
    /// cannot be represented and decodes clipped.
    pub fn rebase(
        &self,
        z: &[f32],
        from_slot: usize,
        from_ref: &[f32],
        to_slot: usize,
        to_ref: &[f32],
        out: &mut [f32],
    ) {
        let a = z.len();
        for (j, (o, &v)) in out.iter_mut().zip(z).enumerate() {
            if self.pose_of(j).is_some() {
                continue;
            }
            let rel = self.is_relative(j);
            let (s0, b0) = self.affine(from_slot, j, a);
            let (s1, b1) = self.affine(to_slot, j, a);
            let same_ref = !rel || from_ref[j].to_bits() == to_ref[j].to_bits();
            if (same_ref && s0.to_bits() == s1.to_bits() && b0.to_bits() == b1.to_bits())
                || s1 == 0.0
            {
                *o = v;
                continue;
            }
            let c = if self.clip.get(j).copied().unwrap_or(false) {
                v.clamp(-1.0, 1.0)
            } else {
                v
            };
            let mut u = c * s0 + b0;
            if rel {
                u += from_ref[j] - to_ref[j];
            }
            *o = (u - b1) / s1;
        }
        for g in &self.poses {
            self.rebase_pose(g, z, from_slot, from_ref, to_slot, to_ref, out);
        }
    }

    /// [`rebase`](Self::rebase) of one pose group: decode at the old slot against the old
    /// reference pose, express the absolute pose relative to the new reference pose, encode
    /// at the new slot. Unchanged statistics and reference: copied bit for bit.
    #[allow(clippy::too_many_arguments)]
    fn rebase_pose(
        &self,
        g: &PoseGroup,
        z: &[f32],
        from_slot: usize,
        from_ref: &[f32],
        to_slot: usize,
        to_ref: &[f32],
        out: &mut [f32],
    ) {
        let (a, r) = (z.len(), g.dims());
        let unchanged = r.clone().all(|j| {
            let ((s0, b0), (s1, b1)) = (self.affine(from_slot, j, a), self.affine(to_slot, j, a));
            from_ref[j].to_bits() == to_ref[j].to_bits()
                && s0.to_bits() == s1.to_bits()
                && b0.to_bits() == b1.to_bits()
        });
        if unchanged {
            out[r.clone()].copy_from_slice(&z[r]);
            return;
        }
        let (mut rel, mut abs) = ([0f32; 9], [0f32; 9]);
        let w = r.len();
        for (k, j) in r.clone().enumerate() {
            let c = if self.clip.get(j).copied().unwrap_or(false) {
                z[j].clamp(-1.0, 1.0)
            } else {
                z[j]
            };
            let (s0, b0) = self.affine(from_slot, j, a);
            rel[k] = c * s0 + b0;
        }
        pose::absolute(g.format, &from_ref[r.clone()], &rel[..w], &mut abs[..w]);
        pose::relative(g.format, &to_ref[r.clone()], &abs[..w], &mut rel[..w]);
        for (k, j) in r.enumerate() {
            let (s1, b1) = self.affine(to_slot, j, a);
            out[j] = if s1 == 0.0 { z[j] } else { (rel[k] - b1) / s1 };
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
    /// The output map decodes per chunk ([`OutputMap::per_slot`]).
    per_slot: bool,
    /// A command was produced from a chunk (per-slot maps: a hold repeats it).
    sent: bool,
    /// Consecutive ticks, since the first action from a chunk, whose command was not a clean
    /// action (a hold, an overrun's `x̂`, or nothing left in the chunk): see
    /// [`ControlState::stalled_ticks`].
    stalled: u64,
    /// An action from a chunk was produced at least once.
    started: bool,
    scratch: Vec<f32>,
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
        cfg.output.validate(h, a)?;
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
            per_slot: cfg.output.per_slot(a),
            sent: false,
            stalled: 0,
            started: false,
            scratch: vec![0.0; a],
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

    /// Set the last-action memory in model space (what a hold sends before any chunk was
    /// executed; with an absolute per-dimension map, what every hold sends until the next
    /// action), e.g. the robot's current targets.
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
    ///
    /// With an absolute, per-dimension output map the model-space action is chosen (from
    /// the current chunk, or the ensemble's weighted mean of model values) and mapped. With
    /// a per-slot map (per-slot statistics or relative dimensions) each chunk's action is
    /// decoded against that chunk's reference and at its own slot, temporal ensembling
    /// averages the decoded commands, and a hold repeats the last command sent.
    pub fn action(&mut self) -> &[f32] {
        if self.per_slot {
            return self.action_per_slot();
        }
        let t = self.tick;
        self.metrics.ticks += 1;
        let held = self.in_flight && matches!(self.cfg.policy, CallPolicy::Sync { .. });
        let mut produced = false;
        let mut clean_out = false;
        if !held {
            if let Some(m) = self.cfg.ensemble {
                produced = self.ensemble_at(t, m);
                clean_out = produced;
            } else if self.has_current {
                if let Some((v, clean)) = self.current.action_at(t) {
                    self.last.copy_from_slice(v);
                    if !clean {
                        self.metrics.overruns += 1;
                    }
                    produced = true;
                    clean_out = clean;
                } else {
                    // Past the end of the chunk: nothing left to execute.
                    self.metrics.overruns += 1;
                }
            }
        }
        self.count_stall(produced, clean_out);
        if !produced {
            self.metrics.holds += 1;
        } else {
            self.executed_since_swap += 1;
        }
        self.tick += 1;
        self.cfg.output.apply(&self.last, &mut self.out);
        &self.out
    }

    fn action_per_slot(&mut self) -> &[f32] {
        let t = self.tick;
        self.metrics.ticks += 1;
        let held = self.in_flight && matches!(self.cfg.policy, CallPolicy::Sync { .. });
        let mut produced = false;
        let mut clean_out = false;
        if !held {
            if let Some(m) = self.cfg.ensemble {
                produced = self.ensemble_decoded_at(t, m);
                clean_out = produced;
            } else if self.has_current {
                let c = &self.current;
                if let (Some(i), Some((v, clean))) = (c.index_of(t), c.action_at(t)) {
                    self.last.copy_from_slice(v);
                    self.cfg.output.decode(v, i, &c.reference, &mut self.out);
                    if !clean {
                        self.metrics.overruns += 1;
                    }
                    produced = true;
                    clean_out = clean;
                } else {
                    self.metrics.overruns += 1;
                }
            }
        }
        self.count_stall(produced, clean_out);
        if !produced {
            self.metrics.holds += 1;
            if !self.sent {
                // Nothing executed yet: the hold action, at slot 0 with no reference.
                self.cfg.output.apply(&self.last, &mut self.out);
            }
        } else {
            self.sent = true;
            self.executed_since_swap += 1;
        }
        self.tick += 1;
        &self.out
    }

    /// The command of the last tick, as [`action`](Self::action) returned it.
    pub fn command(&self) -> &[f32] {
        &self.out
    }

    /// Consecutive ticks, counted from the first action taken from a chunk, whose command
    /// was not a clean action: a hold (sync flow waiting on its call, or nothing to execute),
    /// an overrun's clean estimate `x̂` of a slot with `τ < 1`, or a tick past the end of the
    /// chunk. A clean action resets it; the warm-up before the first chunk does not count.
    /// The real-time driver stops the robot when it exceeds its bound
    /// ([`crate::realtime::RealtimeConfig::stall_limit`]), so a stuck policy never holds the robot on
    /// old data for long.
    pub fn stalled_ticks(&self) -> u64 {
        self.stalled
    }

    fn count_stall(&mut self, produced: bool, clean: bool) {
        if produced && clean {
            self.started = true;
            self.stalled = 0;
        } else if self.started || produced {
            self.started = true;
            self.stalled += 1;
        }
    }

    /// The last action in model space (with an absolute per-dimension map, what a hold
    /// repeats; with a per-slot map a hold repeats the last command, and the ensemble does
    /// not update this).
    pub fn last_action(&self) -> &[f32] {
        &self.last
    }

    /// Temporal ensembling of decoded commands (per-slot maps): each chunk's action at `t`
    /// is decoded with its reference and slot, then weighted.
    fn ensemble_decoded_at(&mut self, t: u64, m: f32) -> bool {
        let cap = self.ring.len();
        let n = (0..self.ring_len)
            .filter(|i| self.ring[(self.ring_head + i) % cap].index_of(t).is_some())
            .count();
        if n == 0 {
            return false;
        }
        pir2_schedule::baselines::ensemble_weights(m, &mut self.weights[..n]);
        self.out.fill(0.0);
        let mut k = 0;
        for i in 0..self.ring_len {
            let c = &self.ring[(self.ring_head + i) % cap];
            if let (Some(slot), Some((v, _))) = (c.index_of(t), c.action_at(t)) {
                self.cfg
                    .output
                    .decode(v, slot, &c.reference, &mut self.scratch);
                let w = self.weights[k];
                for (o, u) in self.out.iter_mut().zip(&self.scratch) {
                    *o += w * u;
                }
                k += 1;
            }
        }
        true
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

#[cfg(test)]
mod output_map_tests {
    use super::*;

    /// `[H = 3, A = 2]` statistics; dimension 0 relative to fast value 4, dimension 1
    /// absolute with the same statistics at every slot.
    fn map() -> OutputMap {
        OutputMap {
            scale: vec![0.5, 2.0, 0.75, 2.0, 1.0, 2.0],
            offset: vec![0.1, -1.0, 0.2, -1.0, 0.3, -1.0],
            clip: vec![true, true],
            reference: vec![Some(4), None],
            poses: Vec::new(),
        }
    }

    /// A relative `xyz_rot6d` pose behind one absolute dimension: `[H = 2, A = 10]`, slot 0
    /// the identity map, slot 1 `u = 2·x + 0.1`; the reference pose is fast values 1..10.
    fn pose_map() -> OutputMap {
        let mut m = OutputMap {
            clip: vec![false; 10],
            reference: (0..10).map(|j| (j > 0).then_some(j)).collect(),
            poses: vec![PoseGroup {
                first: 1,
                format: PoseFormat::XyzRot6d,
            }],
            ..Default::default()
        };
        for slot in 0..2 {
            for _ in 0..10 {
                m.scale.push(if slot == 0 { 1.0 } else { 2.0 });
                m.offset.push(if slot == 0 { 0.0 } else { 0.1 });
            }
        }
        m
    }

    /// Worked by hand (see `pose`): the reference at (1, 2, 0) turned 90° about z, the model's
    /// relative pose (0, 1, 1) turned 90° about z decode to (0, 2, 1) turned 180° about z;
    /// a carried pose rebased onto a new slot and a new reference pose decodes to the same
    /// command; with nothing changed every bit stays.
    #[test]
    fn a_relative_pose_decodes_by_composition_and_rebases_exactly() {
        let m = pose_map();
        m.validate(2, 10).unwrap();
        assert!(m.per_slot(10));
        let obs = [7.0, 1.0, 2.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0];
        let mut r = [0.0; 10];
        m.fill_reference(&obs, &mut r);
        let z = [0.25, 0.0, 1.0, 1.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0];
        let mut u = [0.0; 10];
        m.decode(&z, 0, &r, &mut u);
        let want = [0.25, 0.0, 2.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0];
        assert!(
            u.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6),
            "{u:?}"
        );

        // Slot 0 on reference r → slot 1 on another reference pose.
        let r2 = [0.0, 0.3, -0.2, 0.5, 0.6, 0.0, 0.8, 0.0, 1.0, 0.0];
        let mut z2 = [0.0; 10];
        m.rebase(&z, 0, &r, 1, &r2, &mut z2);
        let mut u2 = [0.0; 10];
        m.decode(&z2, 1, &r2, &mut u2);
        assert!(
            u2.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-5),
            "{u2:?}"
        );
        // Nothing moves: every bit stays.
        let mut z3 = [0.0; 10];
        m.rebase(&z2, 1, &r2, 1, &r2, &mut z3);
        assert_eq!(z3.map(f32::to_bits), z2.map(f32::to_bits));
        // A pose group must be relative and inside the action.
        let mut bad = pose_map();
        bad.reference[3] = None;
        assert!(format!("{}", bad.validate(2, 10).unwrap_err()).contains("poses[0]"));
        let mut bad = pose_map();
        bad.poses[0].first = 2;
        assert!(format!("{}", bad.validate(2, 10).unwrap_err()).contains("poses[0]"));
    }

    #[test]
    fn a_clean_rebase_is_exact_and_the_identity_when_nothing_moves() {
        let m = map();
        let mut r = [0.0; 2];
        m.fill_reference(&[9.0, 9.0, 9.0, 9.0, 0.6], &mut r);
        assert_eq!(r, [0.6, 0.0]);
        // Slot 2 on reference 0.6 → slot 1 on reference 0.9 decodes to the same command.
        let z = [0.4, -0.3];
        let mut z2 = [0.0; 2];
        m.rebase(&z, 2, &[0.6, 0.0], 1, &[0.9, 0.0], &mut z2);
        let (mut u, mut u2) = ([0.0; 2], [0.0; 2]);
        m.decode(&z, 2, &[0.6, 0.0], &mut u);
        m.decode(&z2, 1, &[0.9, 0.0], &mut u2);
        // By hand: 0.4·1.0 + 0.3 + 0.6 = 1.3 = z′·0.75 + 0.2 + 0.9 ⇒ z′ = 0.2/0.75.
        assert!((u[0] - 1.3).abs() < 1e-6 && (u2[0] - 1.3).abs() < 1e-6);
        assert!((z2[0] - 0.2 / 0.75).abs() < 1e-6);
        // The absolute dimension with equal statistics is copied bit for bit.
        assert_eq!(z2[1].to_bits(), z[1].to_bits());
        // Nothing moves: every bit stays.
        let odd = [1.7, -0.0];
        m.rebase(&odd, 1, &[0.6, 0.0], 1, &[0.6, 0.0], &mut z2);
        assert_eq!(z2.map(f32::to_bits), odd.map(f32::to_bits));
        // The model's output is clipped before decoding, as GR00T does.
        m.decode(&[3.0, -5.0], 0, &[0.6, 0.0], &mut u);
        assert_eq!(u, [0.5 + 0.1 + 0.6, -2.0 - 1.0]);
        assert!(m.per_slot(2) && !OutputMap::default().per_slot(2));
    }

    #[test]
    fn output_map_sizes_are_checked_by_name() {
        let mut m = map();
        m.validate(3, 2).unwrap();
        let e = m.validate(4, 2).unwrap_err().to_string();
        assert!(e.contains("output.scale has 6 entries"), "{e}");
        m.scale.truncate(2);
        m.offset.truncate(2);
        m.reference.push(None);
        let e = m.validate(4, 2).unwrap_err().to_string();
        assert!(e.contains("output.reference has 3 entries"), "{e}");
    }
}
