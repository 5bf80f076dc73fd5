//! The streaming inference buffer: one denoising step per call, `d` clean actions out.
//!
//! A call at delay `d` runs in three steps (docs/method.md §1):
//!
//! 1. [`StreamBuffer::plan`]: the front `[0, d)` is what the robot executes during this
//!    call, so any front slot with `τ < 1` is committed to its clean estimate `x̂` and set
//!    to `τ = 1`. The target after the step is the `d`-staircase shifted right by
//!    `e = max(d, 1)`; every position advances to `max(τ_p, target_p)` (nothing ever moves
//!    down), which gives `Δτ_p ≥ 0`.
//! 2. [`StreamBuffer::step`]: with the model's velocity `v` (evaluated on
//!    [`StreamBuffer::model_x`] / [`StreamBuffer::model_tau`]), the Euler update
//!    `x_p += Δτ_p·v_p` makes `[d, d+e)` clean; `x̂ = x + (1−τ)·v` is kept for every slot.
//! 3. [`StreamBuffer::slide`]: once `k` slots have been executed the buffer slides left by
//!    `k` and appends `k` fresh-noise slots (`τ = 0`, new `ε` from the seeded generator).
//!
//! At a steady delay, step + slide reproduces the staircase exactly. After a change to `d'`
//! the buffer is valid after every call and equals the `d'`-staircase again after at most
//! `⌈H/d'⌉` calls at constant `d'` (every pre-change slot has left the buffer).
//!
//! Nothing allocates after construction.
//!
//! ```
//! use pir2_schedule::{StreamBuffer, StreamConfig};
//! let (h, a) = (8, 1);
//! let mut buf = StreamBuffer::new(StreamConfig { horizon: h, action_dim: a, nfe: Some(2), max_delay: 2, ..Default::default() }, 0).unwrap();
//! // Warm start from a clean chunk (normally K-step flow from noise), re-noised to τ*,d0.
//! let target = [0.3f32; 8];
//! buf.warm_start(1, &target).unwrap();
//! assert_eq!(buf.tau(), &[1.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
//! // One call at d = 1 with an exact velocity v = a − ε = (a − x)/(1 − τ):
//! buf.plan(1).unwrap();
//! let v: Vec<f32> = buf.x().iter().zip(buf.tau().iter().flat_map(|t| std::iter::repeat(*t).take(a)))
//!     .zip(target.iter()).map(|((x, t), a)| if t < 1.0 { (a - x) / (1.0 - t) } else { 0.0 }).collect();
//! let out = buf.step(&v).unwrap();
//! assert_eq!((out.start, out.len), (1, 1));           // slot 1 is now clean: emit it
//! assert!((buf.slot(1)[0] - 0.3).abs() < 1e-6);
//! buf.slide(1).unwrap();                                // one slot executed
//! assert_eq!(buf.tau(), &[1.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]); // the staircase again
//! ```

use serde::{Deserialize, Serialize};

use crate::error::{check_len, Error, Result};
use crate::rng::Rng;
use crate::staircase::{Alignment, Staircase};
use crate::HIDDEN_FRONT_TAU;

/// How the inference step shows the front to the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrontMode {
    /// The model sees the committed actions (the paper).
    #[default]
    Visible,
    /// Front slots are zeroed and their `τ` is [`HIDDEN_FRONT_TAU`].
    Hidden,
}

/// Configuration of a [`StreamBuffer`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct StreamConfig {
    /// Chunk length `H`.
    pub horizon: usize,
    /// Action dimension `A`.
    pub action_dim: usize,
    /// NFEs per action `n` (`None` = full-chunk ramp); capped per delay at `n_max(H, d)`.
    pub nfe: Option<usize>,
    /// Staircase alignment.
    pub alignment: Alignment,
    /// Front visibility at inference.
    pub front: FrontMode,
    /// Largest delay the buffer accepts (every `d ≤ max_delay` must give a valid staircase).
    pub max_delay: usize,
}

impl Default for StreamConfig {
    fn default() -> Self {
        Self {
            horizon: 16,
            action_dim: 1,
            nfe: None,
            alignment: Alignment::Fresh,
            front: FrontMode::Visible,
            max_delay: 5,
        }
    }
}

/// What a call produced: slots `[start, start + len)` are clean (`τ = 1`) and are the
/// actions to execute after the in-flight front.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Emitted {
    /// First emitted slot (= the call's delay `d`).
    pub start: usize,
    /// Number of emitted slots (`max(d, 1)`).
    pub len: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Plan {
    d: usize,
    e: usize,
}

/// The streaming buffer (see the module docs).
#[derive(Debug, Clone)]
pub struct StreamBuffer {
    cfg: StreamConfig,
    x: Vec<f32>,
    tau: Vec<f32>,
    xhat: Vec<f32>,
    tau_next: Vec<f32>,
    delta: Vec<f32>,
    x_in: Vec<f32>,
    tau_in: Vec<f32>,
    scratch: Vec<f32>,
    rng: Rng,
    index: u64,
    plan: Option<Plan>,
}

impl StreamBuffer {
    /// A buffer of pure noise (`τ = 0` everywhere); call [`warm_start`](Self::warm_start)
    /// (or [`warm_start_with`](Self::warm_start_with)) before the first call.
    pub fn new(cfg: StreamConfig, seed: u64) -> Result<Self> {
        if cfg.action_dim == 0 {
            return Err(Error::Invalid {
                field: "action_dim",
                message: "must be at least 1".into(),
            });
        }
        if cfg.alignment == Alignment::Paper && cfg.nfe.is_some() {
            return Err(Error::Invalid {
                field: "nfe",
                message: "the paper alignment is the full-chunk ramp; leave nfe unset or use the fresh alignment".into(),
            });
        }
        for d in 0..=cfg.max_delay {
            Self::staircase_for(&cfg, d)?;
        }
        let (h, a) = (cfg.horizon, cfg.action_dim);
        let mut rng = Rng::new(seed);
        let mut x = vec![0.0; h * a];
        rng.fill_normal(&mut x);
        Ok(Self {
            cfg,
            xhat: x.clone(),
            x,
            tau: vec![0.0; h],
            tau_next: vec![0.0; h],
            delta: vec![0.0; h],
            x_in: vec![0.0; h * a],
            tau_in: vec![0.0; h],
            scratch: vec![0.0; h * a],
            rng,
            index: 0,
            plan: None,
        })
    }

    fn staircase_for(cfg: &StreamConfig, d: usize) -> Result<Staircase> {
        let n = match cfg.alignment {
            Alignment::Paper => None,
            Alignment::Fresh => cfg
                .nfe
                .map(|n| n.min(Staircase::n_max(cfg.horizon, d)).max(1)),
        };
        Staircase::new(cfg.horizon, d, n, cfg.alignment)
    }

    /// The staircase `τ*,d` this buffer uses at delay `d` (with `n` capped).
    pub fn staircase(&self, d: usize) -> Result<Staircase> {
        self.check_delay(d)?;
        Self::staircase_for(&self.cfg, d)
    }

    fn check_delay(&self, d: usize) -> Result<()> {
        if d > self.cfg.max_delay {
            return Err(Error::Invalid {
                field: "d",
                message: format!(
                    "delay {d} exceeds the buffer's max_delay {}",
                    self.cfg.max_delay
                ),
            });
        }
        Ok(())
    }

    /// The configuration.
    pub fn config(&self) -> &StreamConfig {
        &self.cfg
    }
    /// The chunk `x`, `[H, A]`.
    pub fn x(&self) -> &[f32] {
        &self.x
    }
    /// Noise levels `τ`, `[H]`.
    pub fn tau(&self) -> &[f32] {
        &self.tau
    }
    /// Clean estimates `x̂ = x + (1−τ)·v` from the last call, `[H, A]`.
    pub fn xhat(&self) -> &[f32] {
        &self.xhat
    }
    /// Slot `p` of `x`.
    pub fn slot(&self, p: usize) -> &[f32] {
        let a = self.cfg.action_dim;
        &self.x[p * a..(p + 1) * a]
    }
    /// Slot `p` of `x̂`.
    pub fn xhat_slot(&self, p: usize) -> &[f32] {
        let a = self.cfg.action_dim;
        &self.xhat[p * a..(p + 1) * a]
    }
    /// Absolute index (count of slots slid out so far) of slot 0.
    pub fn index(&self) -> u64 {
        self.index
    }
    /// Number of leading clean slots (`τ = 1`).
    pub fn clean_prefix(&self) -> usize {
        self.tau.iter().take_while(|&&t| t >= 1.0).count()
    }
    /// `Δτ` planned for the current call (zero outside a call).
    pub fn delta(&self) -> &[f32] {
        &self.delta
    }

    /// Re-noise a clean chunk to `τ*,d0` with fresh `ε`: `x_p = (1−τ*_p)ε_p + τ*_p·clean_p`.
    /// `x̂` becomes `clean`.
    pub fn warm_start(&mut self, d0: usize, clean: &[f32]) -> Result<()> {
        check_len("clean chunk", clean.len(), self.x.len())?;
        let s = self.staircase(d0)?;
        let a = self.cfg.action_dim;
        s.fill(&mut self.tau);
        for p in 0..self.cfg.horizon {
            let t = self.tau[p];
            for j in p * a..(p + 1) * a {
                let eps = self.rng.normal();
                self.x[j] = if t >= 1.0 {
                    clean[j]
                } else {
                    (1.0 - t) * eps + t * clean[j]
                };
            }
        }
        self.xhat.copy_from_slice(clean);
        self.delta.fill(0.0);
        self.plan = None;
        Ok(())
    }

    /// Warm start with `k`-step standard flow from pure noise, then re-noise to `τ*,d0`.
    /// `model(x, tau, v_out)` evaluates the velocity for the whole chunk.
    pub fn warm_start_with<E, F>(
        &mut self,
        d0: usize,
        k: usize,
        mut model: F,
    ) -> std::result::Result<(), E>
    where
        F: FnMut(&[f32], &[f32], &mut [f32]) -> std::result::Result<(), E>,
        E: From<Error>,
    {
        if k == 0 {
            return Err(Error::Invalid {
                field: "k",
                message: "warm start needs at least one step".into(),
            }
            .into());
        }
        self.check_delay(d0)?;
        let mut clean = std::mem::take(&mut self.x_in);
        let mut v = std::mem::take(&mut self.scratch);
        self.rng.fill_normal(&mut clean);
        let dt = 1.0 / k as f32;
        let mut result = Ok(());
        for i in 0..k {
            self.tau_in.fill(i as f32 * dt);
            if let Err(e) = model(&clean, &self.tau_in, &mut v) {
                result = Err(e);
                break;
            }
            for (x, v) in clean.iter_mut().zip(&v) {
                *x += dt * v;
            }
        }
        let ws = match result {
            Ok(()) => self.warm_start(d0, &clean).map_err(E::from),
            Err(e) => Err(e),
        };
        self.x_in = clean;
        self.scratch = v;
        ws
    }

    /// Plan a call at delay `d`: commit the front, compute `Δτ` (see the module docs).
    pub fn plan(&mut self, d: usize) -> Result<()> {
        let s = self.staircase(d)?;
        let a = self.cfg.action_dim;
        for p in 0..d.min(self.cfg.horizon) {
            if self.tau[p] < 1.0 {
                self.x[p * a..(p + 1) * a].copy_from_slice(&self.xhat[p * a..(p + 1) * a]);
                self.tau[p] = 1.0;
            }
        }
        for p in 0..self.cfg.horizon {
            let next = self.tau[p].max(s.tau_after(p));
            self.tau_next[p] = next;
            self.delta[p] = next - self.tau[p];
        }
        if self.cfg.front == FrontMode::Hidden {
            self.x_in.copy_from_slice(&self.x);
            self.tau_in.copy_from_slice(&self.tau);
            self.x_in[..d * a].fill(0.0);
            self.tau_in[..d].fill(HIDDEN_FRONT_TAU);
        }
        self.plan = Some(Plan { d, e: s.emitted() });
        Ok(())
    }

    /// The chunk the model sees this call (front zeroed if hidden).
    pub fn model_x(&self) -> &[f32] {
        match self.cfg.front {
            FrontMode::Visible => &self.x,
            FrontMode::Hidden => &self.x_in,
        }
    }

    /// The `τ` the model sees this call ([`HIDDEN_FRONT_TAU`] on a hidden front).
    pub fn model_tau(&self) -> &[f32] {
        match self.cfg.front {
            FrontMode::Visible => &self.tau,
            FrontMode::Hidden => &self.tau_in,
        }
    }

    /// Apply the Euler step with the model's velocity `v` (`[H, A]`) and update `x̂`.
    /// A non-finite velocity is rejected before anything changes.
    pub fn step(&mut self, v: &[f32]) -> Result<Emitted> {
        let plan = self.plan.ok_or_else(|| Error::Invalid {
            field: "step",
            message: "call plan(d) before step(v)".into(),
        })?;
        check_len("velocity", v.len(), self.x.len())?;
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(Error::Invalid {
                field: "velocity",
                message: format!("non-finite value at flat index {i}"),
            });
        }
        let a = self.cfg.action_dim;
        let slots = self
            .x
            .chunks_exact_mut(a)
            .zip(self.xhat.chunks_exact_mut(a))
            .zip(v.chunks_exact(a));
        for (p, ((xs, hs), vs)) in slots.enumerate() {
            let dt = self.delta[p];
            let t = self.tau_next[p];
            if dt == 0.0 && self.tau[p] >= 1.0 {
                continue; // already clean and untouched (the front): bit-identical, x̂ = x
            }
            self.tau[p] = t;
            // x += Δτ·v; x̂ = x + (1−τ)·v (exactly x for a slot that became clean).
            let c = 1.0 - t;
            for ((x, h), v) in xs.iter_mut().zip(hs.iter_mut()).zip(vs) {
                let xn = *x + dt * v;
                *x = xn;
                *h = xn + c * v;
            }
        }
        self.delta.fill(0.0);
        self.plan = None;
        Ok(Emitted {
            start: plan.d,
            len: plan.e,
        })
    }

    /// Change the action coordinates of every slot, keeping each slot's noise: `map(p, x̂_p,
    /// out)` writes slot `p`'s clean estimate in the new coordinates into `out` (it starts
    /// as a copy of `x̂_p`). A clean slot (`τ = 1`) becomes exactly the mapped value; a
    /// partly denoised slot `x = τ·z + (1−τ)·ε` has its signal part moved through its clean
    /// estimate, `x += τ·(z′ − x̂)`, with `ε` left as it is; `x̂` becomes `z′`. A value the
    /// map leaves unchanged (bit for bit) is not touched, so the identity map changes
    /// nothing. Used to rebase relative actions onto a new reference state between calls;
    /// call it before [`plan`](Self::plan) (it drops a pending plan).
    pub fn remap(&mut self, mut map: impl FnMut(usize, &[f32], &mut [f32])) {
        let a = self.cfg.action_dim;
        for p in 0..self.cfg.horizon {
            let (lo, hi) = (p * a, (p + 1) * a);
            let out = &mut self.scratch[..a];
            out.copy_from_slice(&self.xhat[lo..hi]);
            map(p, &self.xhat[lo..hi], out);
            let t = self.tau[p];
            for j in 0..a {
                let (z, old) = (out[j], self.xhat[lo + j]);
                if z.to_bits() == old.to_bits() {
                    continue;
                }
                if t >= 1.0 {
                    self.x[lo + j] = z;
                } else {
                    self.x[lo + j] += t * (z - old);
                }
                self.xhat[lo + j] = z;
            }
        }
        self.plan = None;
    }

    /// Slide left by `k` executed slots and append `k` fresh-noise slots (`τ = 0`).
    /// The `x̂` of an appended slot holds the last slot's estimate until a call updates it
    /// (so a severe overrun executes a held estimate, never raw noise).
    pub fn slide(&mut self, k: usize) -> Result<()> {
        let (h, a) = (self.cfg.horizon, self.cfg.action_dim);
        if k > h {
            return Err(Error::Invalid {
                field: "k",
                message: format!("cannot slide by {k} > H = {h}"),
            });
        }
        if k == 0 {
            return Ok(());
        }
        self.scratch[..a].copy_from_slice(&self.xhat[(h - 1) * a..]);
        self.x.copy_within(k * a.., 0);
        self.xhat.copy_within(k * a.., 0);
        self.tau.copy_within(k.., 0);
        for p in h - k..h {
            self.tau[p] = 0.0;
            for j in p * a..(p + 1) * a {
                self.x[j] = self.rng.normal();
                self.xhat[j] = self.scratch[j - p * a];
            }
        }
        self.index += k as u64;
        self.plan = None;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg(h: usize, n: Option<usize>, max_delay: usize) -> StreamConfig {
        StreamConfig {
            horizon: h,
            action_dim: 2,
            nfe: n,
            max_delay,
            ..Default::default()
        }
    }

    /// `remap` moves clean slots exactly, keeps a noisy slot's noise (`x − τ·x̂` is
    /// unchanged), and the identity map changes no bit.
    #[test]
    fn remap_moves_the_signal_and_keeps_the_noise() {
        let mut b = StreamBuffer::new(cfg(8, Some(2), 2), 3).unwrap();
        b.warm_start(1, &[0.25; 16]).unwrap();
        let (x0, h0, tau) = (b.x().to_vec(), b.xhat().to_vec(), b.tau().to_vec());
        b.remap(|_, _, _| {});
        assert_eq!((b.x(), b.xhat()), (&x0[..], &h0[..]));
        b.remap(|p, h, out| {
            for (o, v) in out.iter_mut().zip(h) {
                *o = v + 0.5 + p as f32;
            }
        });
        for p in 0..8 {
            for j in 0..2 {
                let i = p * 2 + j;
                let z = 0.25 + 0.5 + p as f32;
                assert_eq!(b.xhat()[i], z);
                if tau[p] >= 1.0 {
                    assert_eq!(b.x()[i], z);
                }
                let noise_before = x0[i] - tau[p] * h0[i];
                let noise_after = b.x()[i] - tau[p] * b.xhat()[i];
                assert!((noise_before - noise_after).abs() < 1e-5, "slot {p}");
            }
        }
        assert!(b.step(&[0.0; 16]).is_err(), "remap drops the plan");
    }

    #[test]
    fn steady_cycle_reproduces_staircase() {
        let mut b = StreamBuffer::new(cfg(16, Some(2), 3), 1).unwrap();
        b.warm_start(2, &[0.0; 32]).unwrap();
        let want = b.staircase(2).unwrap().to_vec();
        for _ in 0..20 {
            b.plan(2).unwrap();
            let e = b.step(&[0.1; 32]).unwrap();
            assert_eq!((e.start, e.len), (2, 2));
            assert_eq!(&b.tau()[2..4], &[1.0, 1.0]);
            b.slide(2).unwrap();
            assert_eq!(b.tau(), &want[..]);
        }
    }

    #[test]
    fn errors_name_the_problem() {
        assert!(matches!(
            StreamBuffer::new(cfg(7, Some(2), 3), 0),
            Err(Error::HorizonTooShort { d: 3, .. })
        ));
        let mut b = StreamBuffer::new(cfg(16, Some(2), 3), 0).unwrap();
        assert!(matches!(
            b.step(&[0.0; 32]),
            Err(Error::Invalid { field: "step", .. })
        ));
        assert!(matches!(b.plan(4), Err(Error::Invalid { field: "d", .. })));
        b.plan(1).unwrap();
        let mut v = [0.0; 32];
        v[5] = f32::NAN;
        let before = b.x().to_vec();
        assert!(matches!(
            b.step(&v),
            Err(Error::Invalid {
                field: "velocity",
                ..
            })
        ));
        assert_eq!(b.x(), &before[..]);
        assert!(matches!(b.step(&[0.0; 31]), Err(Error::Length { .. })));
    }
}
