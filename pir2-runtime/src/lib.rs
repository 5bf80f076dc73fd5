//! # pir2-runtime
//!
//! Turns any [`VelocityModel`] plus a `pir2-schedule` staircase into a reactive controller.
//! It owns the traits every other crate meets (the model, the fast/slow sources, the
//! actuator, the clock, the environment of the lock-step driver) and depends on no ML
//! framework, robot driver or simulator.
#![warn(missing_docs)]

pub mod clock;
pub mod error;
pub mod io;
pub mod model;

pub use clock::{Clock, MockClock, Nanos, SystemClock};
pub use error::{Error, Result};
pub use io::{
    Actuator, EnvStep, Environment, FastSource, SlowEncoder, SlowFeatures, SlowFrame, SlowSource,
};
pub use model::{ModelInput, SlowInput, VelocityModel};
