//! Proximal policy optimisation (PPO) for the paper's Leap-cube variant, on the CPU, in C
//! MuJoCo: the expert whose demonstrations the study clones.
//!
//! * [`task`]: the paper environment as PPO sees it — the actor's noisy 41-d observation
//!   (optionally plus the previous action), the critic's privileged observation, the
//!   playground's reward terms with the orientation error to the nearest blue-side-up goal.
//! * [`Trainer`]: batched environments on scoped threads, GAE, clipped surrogate, Adam,
//!   running observation normalisation, seeded and resumable checkpoints
//!   (safetensors). Results do not depend on the thread count.
//! * [`PpoExpert`]: the trained actor as a deterministic function `act(fast, slow)` (the
//!   clamped policy mean), with its small weights file, and [`evaluate`] on the paper env.
//!
//! The networks are small multi-layer perceptrons with hand-written backpropagation
//! ([`mlp`]); the matrix products run on the `gemm` crate.
//!
//! Recipe (defaults of [`PpoConfig`]), after MuJoCo Playground's LeapCubeReorient PPO
//! (`brax` PPO: 8192 environments, unroll 40, 32 minibatches, 4 epochs, learning rate
//! 3e-4, entropy cost 1e-2, discount 0.99, 512-256-128 swish networks, observation
//! normalisation, asymmetric critic on a privileged state) scaled to a 2-core CPU: 128
//! environments × 64 steps per iteration, 4 minibatches × 4 epochs, γ 0.99, λ 0.95,
//! clip 0.2, gradient-norm bound 1, 256-128-64 swish networks, a state-independent σ
//! (initially 0.25) and entropy 1e-3. The playground's entropy cost 1e-2 with this
//! parametrisation made σ grow without bound (the noisy policy succeeds by tumbling the
//! cube while its mean does not improve), and σ = 0.5 at 50 Hz is several times the useful
//! action size, so both were lowered.

pub mod algo;
mod expert;
mod io;
pub mod mlp;
pub mod norm;
pub mod task;
mod trainer;

pub use expert::{
    evaluate, evaluate_delayed, nearest_goal_rows, EvalReport, OrientationInput, PpoExpert, Squash,
    EXPERT_FORMAT,
};
pub use trainer::{EpisodeRecord, IterStats, PpoConfig, Trainer, CHECKPOINT_FORMAT};
