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

/// One raw frame of the slow channel: an image and/or a prompt, with its capture time.
#[derive(Debug, Clone, Default)]
pub struct SlowFrame {
    /// Capture time on the runtime's clock.
    pub t_capture: Nanos,
    /// Image bytes (layout defined by the source, e.g. HWC u8 RGB), may be empty.
    pub image: Vec<u8>,
    /// Image height and width, if an image is present.
    pub image_hw: (usize, usize),
    /// Raw slow observation values (e.g. a camera-estimated object pose), may be empty.
    pub values: Vec<f32>,
    /// The language prompt, may be empty.
    pub prompt: String,
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
