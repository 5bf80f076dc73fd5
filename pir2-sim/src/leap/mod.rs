//! The LEAP-hand cube reorientation task in MuJoCo and its MPC expert.
//!
//! Placeholder; filled in below.

mod error;
pub mod scene;

pub use error::{LeapError, Result};
