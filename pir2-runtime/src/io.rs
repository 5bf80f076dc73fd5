//! The traits the runtime meets at its edges: robots (fast source, actuator), cameras and
//! backbones (slow source, slow encoder), and simulated environments (lock-step driver).
//!
//! The control-step traits ([`FastSource`], [`Actuator`]) are synchronous and write into
//! caller-owned buffers: the control thread must neither allocate nor await. The slow
//! channel runs on its own worker, where I/O and long computations are natural, so its
//! traits are `async` (via `async-trait`).

use crate::clock::Nanos;
use crate::error::Result;

/// Fresh proprioception, read once per control tick (the fast channel).
pub trait FastSource: Send {
    /// Dimension of one proprioceptive observation.
    fn dim(&self) -> usize;
    /// Write the newest observation into `out` (`out.len() == dim()`) and return the time
    /// it was measured, on the runtime's clock.
    fn read(&mut self, out: &mut [f32]) -> Result<Nanos>;
}

/// Something that executes one action per control tick (a robot, a safety layer, a sim).
pub trait Actuator: Send {
    /// Dimension of one action.
    fn dim(&self) -> usize;
    /// Send one action (`action.len() == dim()`).
    fn send(&mut self, action: &[f32]) -> Result<()>;
    /// Stop safely (hold position / disable motion). Called on shutdown and on safety stops.
    fn stop(&mut self) -> Result<()>;
}

/// One camera image of the slow channel.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct View {
    /// Image bytes (layout defined by the source, e.g. HWC `u8` RGB).
    pub image: Vec<u8>,
    /// Image height and width.
    pub hw: (usize, usize),
}

/// One raw frame of the slow channel: camera images and/or a prompt, with its capture time.
#[derive(Debug, Clone, Default)]
pub struct SlowFrame {
    /// Capture time on the runtime's clock. A frame joined from several cameras carries the
    /// oldest view's time, so the slow channel's age `d_vis` is never understated.
    pub t_capture: Nanos,
    /// Camera images, one per view in the order the encoder expects (empty when the slow
    /// channel carries none).
    pub views: Vec<View>,
    /// Raw slow observation values (e.g. a camera-estimated object pose), may be empty.
    pub values: Vec<f32>,
    /// The language prompt, may be empty.
    pub prompt: String,
}

impl SlowFrame {
    /// A frame of one camera image captured at `t_capture`.
    pub fn image(t_capture: Nanos, image: Vec<u8>, hw: (usize, usize)) -> Self {
        SlowFrame {
            t_capture,
            views: vec![View { image, hw }],
            ..Default::default()
        }
    }
}

/// Encoded slow features with the capture time of the frame they were computed from.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SlowFeatures {
    /// Capture time of the underlying frame (not the time encoding finished).
    pub t_capture: Nanos,
    /// Flat features: `[S]` for a vector, `[T, D]` row-major for tokens.
    pub data: Vec<f32>,
    /// Number of tokens (1 for a plain vector).
    pub tokens: usize,
    /// Width of one token (the vector length for a plain vector).
    pub dim: usize,
}

/// A camera / prompt source for the slow channel.
#[async_trait::async_trait]
pub trait SlowSource: Send {
    /// Capture the next frame.
    async fn capture(&mut self) -> Result<SlowFrame>;
}

#[async_trait::async_trait]
impl SlowSource for Box<dyn SlowSource> {
    async fn capture(&mut self) -> Result<SlowFrame> {
        (**self).capture().await
    }
}

/// Several camera sources joined into one multi-view frame: each capture takes one frame
/// from every source in turn and returns their views in source order. The joined frame
/// carries the **oldest** view's capture time (so `d_vis` counts from the stalest image),
/// the sources' values concatenated, and the first non-empty prompt. A source's error ends
/// the capture with that error (a stale or missing view never passes as a fresh frame),
/// and a source that delivers no image is an error naming its position.
pub struct Views<S> {
    sources: Vec<S>,
}

impl<S> std::fmt::Debug for Views<S> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Views")
            .field("sources", &self.sources.len())
            .finish()
    }
}

impl<S: SlowSource> Views<S> {
    /// Join `sources` (at least one), in view order.
    pub fn new(sources: Vec<S>) -> Result<Self> {
        if sources.is_empty() {
            return Err(crate::Error::Config(
                "a multi-view slow source needs at least one camera".into(),
            ));
        }
        Ok(Self { sources })
    }

    /// Number of joined sources.
    pub fn len(&self) -> usize {
        self.sources.len()
    }

    /// Never true (a `Views` holds at least one source).
    pub fn is_empty(&self) -> bool {
        self.sources.is_empty()
    }
}

#[async_trait::async_trait]
impl<S: SlowSource> SlowSource for Views<S> {
    async fn capture(&mut self) -> Result<SlowFrame> {
        let mut out = SlowFrame {
            t_capture: Nanos::MAX,
            ..Default::default()
        };
        for (k, src) in self.sources.iter_mut().enumerate() {
            let f = src.capture().await?;
            if f.views.is_empty() {
                return Err(crate::Error::Io {
                    device: format!("camera view {k}"),
                    message: "delivered a frame without an image".into(),
                });
            }
            out.t_capture = out.t_capture.min(f.t_capture);
            out.views.extend(f.views);
            out.values.extend(f.values);
            if out.prompt.is_empty() {
                out.prompt = f.prompt;
            }
        }
        Ok(out)
    }
}

/// A backbone that turns a slow frame into features (a VLM, an image encoder, or identity).
#[async_trait::async_trait]
pub trait SlowEncoder: Send {
    /// Encode one frame. The returned features must carry `frame.t_capture`.
    async fn encode(&mut self, frame: SlowFrame) -> Result<SlowFeatures>;
}

/// Sizes and timing of an [`Environment`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EnvSpec {
    /// Fast (proprioceptive) observation dimension.
    pub fast_dim: usize,
    /// Slow (camera) observation dimension.
    pub slow_dim: usize,
    /// Action dimension.
    pub action_dim: usize,
    /// Control period in nanoseconds.
    pub control_period: Nanos,
    /// Episode length in control steps.
    pub max_steps: usize,
}

/// Outcome of one environment step.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct EnvStep {
    /// The episode ended (success, failure or time-out).
    pub done: bool,
    /// The episode ended in success (only meaningful when `done`).
    pub success: bool,
    /// Task reward for this step (informational).
    pub reward: f32,
}

/// A simulated task for the lock-step driver. Observations are the *current* noisy
/// sensor readings; the driver itself delays the slow channel by `d_vis` ticks.
pub trait Environment: Send {
    /// Sizes and timing.
    fn spec(&self) -> EnvSpec;
    /// Start a new episode; all randomness of the episode derives from `seed`.
    fn reset(&mut self, seed: u64);
    /// Write the current fast and slow observations (with sensing noise).
    fn observe(&mut self, fast: &mut [f32], slow: &mut [f32]);
    /// Apply one action for one control period.
    fn step(&mut self, action: &[f32]) -> EnvStep;
}

/// An [`Environment`] whose slow observation is the last `frames` slow observations of the
/// inner one, oldest first (`frames × slow_dim` values): `n_obs` for the slow channel. The
/// first observation of an episode fills every frame (the history is padded by repeating
/// it, as the fast history is). A new frame enters on the first [`Environment::observe`]
/// after each [`Environment::step`]; observing again before the next step replaces the
/// newest frame, so a driver that observes every tick (as the lock-step driver does) gets one
/// frame per tick.
///
/// The lock-step driver delays the whole stacked observation, so a slow input `d` ticks old
/// is the frames `t − d − frames + 1 ..= t − d`, the layout a dataset's episodes get from
/// stacking their slow observations the same way.
#[derive(Debug, Clone)]
pub struct SlowFrames<E> {
    inner: E,
    frames: usize,
    hist: Vec<f32>,
    scratch: Vec<f32>,
    /// Whether `hist` holds this episode's frames (false right after a reset).
    filled: bool,
    stepped: bool,
}

impl<E: Environment> SlowFrames<E> {
    /// Wrap `inner`, stacking `frames` (≥ 1) slow observations.
    ///
    /// # Panics
    /// If `frames` is 0.
    pub fn new(inner: E, frames: usize) -> Self {
        assert!(frames >= 1, "at least one slow frame");
        let s = inner.spec().slow_dim;
        Self {
            inner,
            frames,
            hist: vec![0.0; frames * s],
            scratch: vec![0.0; s],
            filled: false,
            stepped: false,
        }
    }
    /// The wrapped environment.
    pub fn inner(&self) -> &E {
        &self.inner
    }
    /// The wrapped environment, mutably.
    pub fn inner_mut(&mut self) -> &mut E {
        &mut self.inner
    }
}

impl<E: Environment> Environment for SlowFrames<E> {
    fn spec(&self) -> EnvSpec {
        let s = self.inner.spec();
        EnvSpec {
            slow_dim: s.slow_dim * self.frames,
            ..s
        }
    }
    fn reset(&mut self, seed: u64) {
        self.inner.reset(seed);
        self.filled = false;
        self.stepped = false;
    }
    fn observe(&mut self, fast: &mut [f32], slow: &mut [f32]) {
        let s = self.scratch.len();
        self.inner.observe(fast, &mut self.scratch);
        if !self.filled {
            for k in 0..self.frames {
                self.hist[k * s..(k + 1) * s].copy_from_slice(&self.scratch);
            }
            self.filled = true;
        } else {
            if self.stepped {
                self.hist.copy_within(s.., 0);
            }
            let last = (self.frames - 1) * s;
            self.hist[last..].copy_from_slice(&self.scratch);
        }
        self.stepped = false;
        slow.copy_from_slice(&self.hist);
    }
    fn step(&mut self, action: &[f32]) -> EnvStep {
        self.stepped = true;
        self.inner.step(action)
    }
}

#[cfg(test)]
mod slow_frames_tests {
    use super::*;

    /// Slow observation = [tick, 10·tick]; fast = [tick].
    struct Counter {
        tick: u64,
    }
    impl Environment for Counter {
        fn spec(&self) -> EnvSpec {
            EnvSpec {
                fast_dim: 1,
                slow_dim: 2,
                action_dim: 1,
                control_period: 1,
                max_steps: 10,
            }
        }
        fn reset(&mut self, seed: u64) {
            self.tick = seed;
        }
        fn observe(&mut self, fast: &mut [f32], slow: &mut [f32]) {
            fast[0] = self.tick as f32;
            slow.copy_from_slice(&[self.tick as f32, 10.0 * self.tick as f32]);
        }
        fn step(&mut self, _action: &[f32]) -> EnvStep {
            self.tick += 1;
            EnvStep::default()
        }
    }

    #[test]
    fn stacks_one_frame_per_tick_oldest_first_padded_at_the_start() {
        let mut env = SlowFrames::new(Counter { tick: 0 }, 3);
        assert_eq!(env.spec().slow_dim, 6);
        let (mut f, mut s) = ([0.0], [0.0; 6]);
        env.reset(5);
        env.observe(&mut f, &mut s);
        assert_eq!(s, [5.0, 50.0, 5.0, 50.0, 5.0, 50.0]);
        // Observing twice in one tick does not shift the history.
        env.observe(&mut f, &mut s);
        assert_eq!(s, [5.0, 50.0, 5.0, 50.0, 5.0, 50.0]);
        env.step(&[0.0]);
        env.observe(&mut f, &mut s);
        assert_eq!(s, [5.0, 50.0, 5.0, 50.0, 6.0, 60.0]);
        env.step(&[0.0]);
        env.step(&[0.0]); // a tick not observed is not in the history
        env.observe(&mut f, &mut s);
        assert_eq!(s, [5.0, 50.0, 6.0, 60.0, 8.0, 80.0]);
        assert_eq!(f, [8.0]);
        // A reset starts a new padded history.
        env.reset(1);
        env.observe(&mut f, &mut s);
        assert_eq!(s, [1.0, 10.0, 1.0, 10.0, 1.0, 10.0]);
    }
}
