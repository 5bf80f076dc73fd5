//! Rolling the expert and recording demonstrations in memory.
//!
//! Episode `i` of a collection with seed `s` uses environment seed
//! `Rng::derive(s, 2i).next_u64()` and expert seed `Rng::derive(s, 2i + 1).next_u64()`, so a
//! collection can be resumed (or split) by episode index and yields the same episodes.
//! Frames hold plain `Vec<f32>`s, ready for a LeRobot-style writer: `observation.state` =
//! `fast` (32), the slow cube observation `slow` (9, current, *not* delayed — the runtime
//! adds the delay), `action` (16).

use std::ops::Range;

use pir2_runtime::Environment;
use pir2_schedule::Rng;

use super::env::{LeapConfig, LeapCubeEnv};
use super::error::Result;
use super::model::{LeapModel, NU};
use super::mpc::{MpcConfig, MpcExpert};

/// What to collect.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CollectConfig {
    /// The environment (normally [`LeapConfig::paper`]).
    pub env: LeapConfig,
    /// The expert.
    pub mpc: MpcConfig,
    /// Collection seed.
    pub seed: u64,
}

impl Default for CollectConfig {
    fn default() -> Self {
        Self {
            env: LeapConfig::paper(),
            mpc: MpcConfig::default(),
            seed: 0,
        }
    }
}

/// One control step of a demonstration.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Episode index within the collection.
    pub episode_index: usize,
    /// Frame index within the episode (0-based).
    pub frame_index: usize,
    /// Fast (proprioceptive) observation before the action.
    pub fast: Vec<f32>,
    /// Slow (cube) observation before the action, undelayed.
    pub slow: Vec<f32>,
    /// The expert's action (`[−1, 1]^16`).
    pub action: Vec<f32>,
    /// Reward of the step.
    pub reward: f32,
    /// The episode ended with this step.
    pub done: bool,
}

/// One recorded episode.
#[derive(Debug, Clone, PartialEq)]
pub struct Episode {
    /// Episode index within the collection.
    pub index: usize,
    /// Seed passed to [`Environment::reset`].
    pub env_seed: u64,
    /// The frames, in order.
    pub frames: Vec<Frame>,
    /// The episode ended in success.
    pub success: bool,
}

/// Environment and expert seeds of episode `index` in a collection seeded with `seed`.
pub fn episode_seeds(seed: u64, index: usize) -> (u64, u64) {
    let i = index as u64;
    (
        Rng::derive(seed, 2 * i).next_u64(),
        Rng::derive(seed, 2 * i + 1).next_u64(),
    )
}

/// Roll the MPC expert for the episodes with indices in `episodes` and return them;
/// `progress` sees each episode as it completes.
pub fn collect(
    model: &LeapModel,
    cfg: &CollectConfig,
    episodes: Range<usize>,
    mut progress: impl FnMut(&Episode),
) -> Result<Vec<Episode>> {
    let mut env = LeapCubeEnv::new(model, cfg.env)?;
    let mut expert = MpcExpert::new(model, cfg.mpc, 0)?;
    let (fd, sd) = cfg.env.obs_dims();
    let mut out = Vec::with_capacity(episodes.len());
    for index in episodes {
        let (env_seed, expert_seed) = episode_seeds(cfg.seed, index);
        env.reset(env_seed);
        expert.reset(&env, expert_seed);
        let mut frames = Vec::new();
        let mut success = false;
        for frame_index in 0..cfg.env.max_steps {
            let mut fast = vec![0.0; fd];
            let mut slow = vec![0.0; sd];
            env.observe(&mut fast, &mut slow);
            let action = expert.act(&env);
            let st = env.step(&action);
            frames.push(Frame {
                episode_index: index,
                frame_index,
                fast,
                slow,
                action: action[..NU].to_vec(),
                reward: st.reward,
                done: st.done,
            });
            if st.done {
                success = st.success;
                break;
            }
        }
        let ep = Episode {
            index,
            env_seed,
            frames,
            success,
        };
        progress(&ep);
        out.push(ep);
    }
    Ok(out)
}
