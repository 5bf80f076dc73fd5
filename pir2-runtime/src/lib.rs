//! # pir2-runtime
//!
//! Turns any [`VelocityModel`] plus a `pir2-schedule` staircase into a reactive controller.
//! It owns the traits every other crate meets (the model, the fast/slow sources, the
//! actuator, the clock, the environment of the lock-step driver) and depends on no ML
//! framework, robot driver or simulator.
//!
//! One state machine, two drivers (docs/method.md §2):
//! - [`head::ActionHead`] turns a [`head::Snapshot`] into a [`chunk::Chunk`] (one NFE for
//!   πR²; `K` steps for the baselines) and owns the rolling latency window;
//! - [`control::ControlState`] picks the action of each tick (swap at the elapsed index,
//!   `x̂` on overrun, temporal ensembling, sync holds);
//! - [`realtime`] runs them on threads against a [`Clock`]; [`lockstep`] steps them with an
//!   [`Environment`] where a call takes an injected number of ticks, and [`batched`] runs
//!   a study cell's lock-step episodes side by side with one batched model call per round.
//!
//! # Quick start
//!
//! A 50 Hz πR² loop around your own model and robot ([`builder`]; `examples/realtime_50hz.rs`
//! adds an asynchronous camera channel):
//!
//! ```
//! use std::time::Duration;
//! use pir2_runtime::testing::{FakeRobot, SleepyModel};
//! use pir2_runtime::{Mode, Realtime, SystemClock};
//!
//! # fn main() -> pir2_runtime::Result<()> {
//! let clock = std::sync::Arc::new(SystemClock::new());
//! let robot = FakeRobot::new(6, clock.clone()); // implements FastSource + Actuator
//! let model = SleepyModel { latency: Duration::from_millis(2) }; // implements VelocityModel
//! let metrics = Realtime::builder(model)
//!     .chunk(16, 6)
//!     .fast(12, 2)
//!     .hz(50.0)
//!     .mode(Mode::pir2_async(2))
//!     .max_ticks(50)
//!     .clock(clock)
//!     .run(robot.clone(), robot)?;
//! println!("{} ticks, {} overruns", metrics.ticks, metrics.overruns);
//! # Ok(()) }
//! ```
#![warn(missing_docs)]

pub mod batched;
pub mod bench;
pub mod builder;
pub mod chunk;
pub mod clock;
pub mod control;
pub mod error;
pub mod head;
pub mod io;
pub mod lockstep;
pub mod metrics;
pub mod mode;
pub mod model;
pub mod policy;
pub mod pose;
pub mod realtime;
#[cfg(feature = "remote")]
pub mod remote;
pub mod testing;
pub mod window;

pub use batched::eval_cell_batched;
pub use builder::{Realtime, RealtimeBuilder};
pub use chunk::Chunk;
pub use clock::{Clock, MockClock, Nanos, SystemClock};
pub use control::{CallPolicy, ControlConfig, ControlState, OutputMap, PoseGroup};
pub use error::{panic_message, Error, Result, ShapeMismatch};
pub use head::{ActionHead, HeadMode, HeadSpec, Snapshot};
pub use io::{
    Actuator, EnvSpec, EnvStep, Environment, FastSource, SlowEncoder, SlowFeatures, SlowFrame,
    SlowFrames, SlowSource, View, Views,
};
pub use lockstep::{eval_cell, EpisodeResult, LockstepDriver, LockstepTiming, StudyCell};
pub use metrics::{CallRecord, Histogram, Percentiles, RunMetrics, RunTrace};
pub use mode::{EffectiveDelays, Mode};
pub use model::{ModelInput, SlowInput, SlowSpec, StopSignal, VelocityModel};
/// The schedule's public types a robot program names (so it needs no direct dependency on
/// `pir2-schedule`).
pub use pir2_schedule::{Alignment, FrontMode, Staircase};
pub use policy::{DelayLaw, Deployment, Policy, Recipe};
pub use window::LatencyWindow;
