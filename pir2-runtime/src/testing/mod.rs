//! Small stand-ins for tests, examples and benchmarks: a fake robot, a camera stub and
//! simple models. They are real implementations of the runtime's traits, not mocks of
//! its internals.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use crate::clock::{Clock, Nanos};
use crate::error::Result;
use crate::io::{Actuator, FastSource, SlowEncoder, SlowFeatures, SlowFrame, SlowSource};
use crate::model::{ModelInput, VelocityModel};

/// A first-order fake robot: each command moves the joints halfway to it. Proprioception
/// is `[q, q − last command]`.
#[derive(Debug, Clone)]
pub struct FakeRobot {
    q: Vec<f32>,
    cmd: Vec<f32>,
    clock: Arc<dyn Clock>,
    /// Commands received.
    pub sent: Arc<AtomicU64>,
    /// `stop()` calls received.
    pub stops: Arc<AtomicU64>,
}

impl FakeRobot {
    /// A robot with `dof` joints at zero.
    pub fn new(dof: usize, clock: Arc<dyn Clock>) -> Self {
        Self {
            q: vec![0.0; dof],
            cmd: vec![0.0; dof],
            clock,
            sent: Arc::new(AtomicU64::new(0)),
            stops: Arc::new(AtomicU64::new(0)),
        }
    }
}

impl FastSource for FakeRobot {
    fn dim(&self) -> usize {
        2 * self.q.len()
    }
    fn read(&mut self, out: &mut [f32]) -> Result<Nanos> {
        let n = self.q.len();
        for i in 0..n {
            out[i] = self.q[i];
            out[n + i] = self.q[i] - self.cmd[i];
        }
        Ok(self.clock.now())
    }
}

impl Actuator for FakeRobot {
    fn dim(&self) -> usize {
        self.q.len()
    }
    fn send(&mut self, action: &[f32]) -> Result<()> {
        for ((q, c), a) in self.q.iter_mut().zip(self.cmd.iter_mut()).zip(action) {
            *c = *a;
            *q += 0.5 * (*a - *q);
        }
        self.sent.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }
    fn stop(&mut self) -> Result<()> {
        self.cmd.copy_from_slice(&self.q);
        self.stops.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }
}

/// A camera stub producing `dim` values per frame every `period`, stamped with `clock`.
#[derive(Debug)]
pub struct CameraStub {
    clock: Arc<dyn Clock>,
    period: Duration,
    dim: usize,
    frame: u64,
}

impl CameraStub {
    /// A stub camera.
    pub fn new(clock: Arc<dyn Clock>, period: Duration, dim: usize) -> Self {
        Self {
            clock,
            period,
            dim,
            frame: 0,
        }
    }
}

#[async_trait::async_trait]
impl SlowSource for CameraStub {
    async fn capture(&mut self) -> Result<SlowFrame> {
        std::thread::sleep(self.period);
        self.frame += 1;
        Ok(SlowFrame {
            t_capture: self.clock.now(),
            values: vec![self.frame as f32; self.dim],
            ..Default::default()
        })
    }
}

/// An encoder that passes the frame's values through after `latency` (a stand-in for a
/// backbone).
#[derive(Debug, Clone, Copy)]
pub struct PassThroughEncoder {
    /// Simulated backbone time.
    pub latency: Duration,
}

#[async_trait::async_trait]
impl SlowEncoder for PassThroughEncoder {
    async fn encode(&mut self, frame: SlowFrame) -> Result<SlowFeatures> {
        std::thread::sleep(self.latency);
        let dim = frame.values.len();
        Ok(SlowFeatures {
            t_capture: frame.t_capture,
            data: frame.values,
            tokens: 1,
            dim,
        })
    }
}

/// A model whose velocity pulls every slot towards zero, after sleeping `latency` per call
/// (a stand-in with a known cost).
#[derive(Debug, Clone, Copy)]
pub struct SleepyModel {
    /// Time each call takes.
    pub latency: Duration,
}

impl VelocityModel for SleepyModel {
    fn backend(&self) -> &'static str {
        "sleepy"
    }
    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        if !self.latency.is_zero() {
            std::thread::sleep(self.latency);
        }
        for (o, x) in out.iter_mut().zip(input.x) {
            *o = -x;
        }
        Ok(())
    }
}

#[cfg(feature = "remote")]
pub mod rogue;
