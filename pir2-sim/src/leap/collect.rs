//! Rolling an expert and recording demonstrations in memory.
//!
//! Any [`Expert`] can demonstrate: the sampling MPC ([`MpcExpert`], privileged state) or a
//! trained policy used deterministically ([`PpoExpert`](super::ppo::PpoExpert), which acts on
//! exactly the observation that is recorded with its action).
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
use super::model::{LeapModel, NU};
use super::mpc::{MpcConfig, MpcExpert};
use crate::error::Result;

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

/// A demonstrator: called once per episode after the environment's reset, then once per
/// control step with the observation the environment just produced (the one recorded).
pub trait Expert {
    /// Start an episode; `seed` is the episode's expert seed ([`episode_seeds`]).
    fn begin(&mut self, env: &LeapCubeEnv, seed: u64);
    /// The action (`[−1, 1]^16`) for this step.
    fn act(&mut self, env: &LeapCubeEnv, fast: &[f32], slow: &[f32]) -> [f32; NU];
}

impl Expert for MpcExpert {
    fn begin(&mut self, env: &LeapCubeEnv, seed: u64) {
        self.reset(env, seed);
    }

    /// Plans on the privileged simulation state; the observation is not used.
    fn act(&mut self, env: &LeapCubeEnv, _fast: &[f32], _slow: &[f32]) -> [f32; NU] {
        MpcExpert::act(self, env)
    }
}

impl Expert for super::ppo::PpoExpert {
    fn begin(&mut self, _env: &LeapCubeEnv, _seed: u64) {
        self.reset();
    }

    /// Deterministic: a function of the observation (and of its own previous action when
    /// the weights use it).
    fn act(&mut self, _env: &LeapCubeEnv, fast: &[f32], slow: &[f32]) -> [f32; NU] {
        super::ppo::PpoExpert::act(self, fast, slow)
    }
}

/// Roll the MPC expert for the episodes with indices in `episodes` and return them;
/// `progress` sees each episode as it completes.
pub fn collect(
    model: &LeapModel,
    cfg: &CollectConfig,
    episodes: Range<usize>,
    progress: impl FnMut(&Episode),
) -> Result<Vec<Episode>> {
    let mut expert = MpcExpert::new(model, cfg.mpc, 0)?;
    collect_with(model, cfg.env, cfg.seed, &mut expert, episodes, progress)
}

/// Roll `expert` on the environment `env_cfg` for the episodes with indices in `episodes`
/// of a collection seeded with `seed` ([`episode_seeds`]) and return them; `progress` sees
/// each episode as it completes.
pub fn collect_with(
    model: &LeapModel,
    env_cfg: LeapConfig,
    seed: u64,
    expert: &mut dyn Expert,
    episodes: Range<usize>,
    mut progress: impl FnMut(&Episode),
) -> Result<Vec<Episode>> {
    let mut env = LeapCubeEnv::new(model, env_cfg)?;
    let (fd, sd) = env_cfg.obs_dims();
    let mut out = Vec::with_capacity(episodes.len());
    for index in episodes {
        let (env_seed, expert_seed) = episode_seeds(seed, index);
        env.reset(env_seed);
        expert.begin(&env, expert_seed);
        let mut frames = Vec::new();
        let mut success = false;
        for frame_index in 0..env_cfg.max_steps {
            let mut fast = vec![0.0; fd];
            let mut slow = vec![0.0; sd];
            env.observe(&mut fast, &mut slow);
            let action = expert.act(&env, &fast, &slow);
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
