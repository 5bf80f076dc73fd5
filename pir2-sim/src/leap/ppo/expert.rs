//! The trained policy as a deterministic expert: `act(observation) → action`, the clamped
//! mean of the Gaussian policy, and its evaluation on the paper's environment.
//!
//! Weights file (safetensors, format `pir2-ppo-expert-v1`): tensors `actor` (the flat MLP
//! parameters: per layer the `out × in` row-major weight matrix, then the bias), `obs_mean`
//! and `obs_std` (the frozen observation normalisation, `x ↦ clip((x − mean)/std, ±10)`),
//! `log_std` (the exploration noise, informational); metadata `format`, `sizes` (layer
//! widths, comma-separated, input first), `activation` (`silu` or `tanh`), `prev_action`
//! (`true` if the observation ends with the previous action), `iteration`, `env_steps`.
//!
//! Optional metadata (absent = the first value, what the PPO trainer writes):
//! - `squash` = `clamp` | `tanh`: the action is `clamp(μ, ±1)` or `tanh(μ)`;
//! - `orientation` = `absolute` | `nearest_goal`: the cube-orientation input (observation
//!   values 35..41, rows 2–3 of the rotation matrix `R` of the sensed cube quaternion) is fed
//!   as is, or replaced by rows 2–3 of `R·Gᵀ`, the rotation from the nearest of the four
//!   blue-side-up goals `G` (largest `tr(R·Gᵀ)`; row 1 of `R` is the cross product of rows 2
//!   and 3) — the goal-relative feature of MuJoCo Playground's LeapCubeReorient policies,
//!   computed from the paper's observation alone;
//! - `obs_clip` = a positive number or `none`: the bound of the normalised observation
//!   (default 10).
//!
//! The two options let a MuJoCo Playground LeapCubeReorient policy (a 512-256-128 swish MLP
//! with a tanh head over the playground's 57-d observation, which is the paper's 41 values
//! with a goal-relative orientation plus the previous action) run as an expert on the paper's
//! environment; `scripts/playground-expert.py` converts its published ONNX export.

use std::ops::Range;
use std::path::Path;

use pir2_runtime::Environment;

use crate::leap::{episode_seeds, LeapConfig, LeapCubeEnv, LeapModel, NU};

use super::io::{format_err, TensorReader, TensorWriter};
use super::mlp::{Activation, Mlp};
use super::norm::FrozenNorm;
use super::task::{actor_dim, BASE_OBS_DIM};
use crate::error::Result;
use crate::leap::math::{blue_side_up_goals, rot_rows_23};

/// How the actor's output becomes an action.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Squash {
    /// `clamp(μ, −1, 1)` (the PPO trainer's Gaussian mean).
    Clamp,
    /// `tanh(μ)` (a tanh-squashed policy head).
    Tanh,
}

impl Squash {
    fn name(self) -> &'static str {
        match self {
            Squash::Clamp => "clamp",
            Squash::Tanh => "tanh",
        }
    }
}

/// Which cube-orientation feature the actor sees (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OrientationInput {
    /// Rows 2–3 of the sensed cube rotation, as the environment observes them.
    Absolute,
    /// Rows 2–3 of the rotation from the nearest blue-side-up goal.
    NearestGoal,
}

impl OrientationInput {
    fn name(self) -> &'static str {
        match self {
            OrientationInput::Absolute => "absolute",
            OrientationInput::NearestGoal => "nearest_goal",
        }
    }
}

fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Rotation matrices (rows) of the four blue-side-up goals, computed once.
fn goal_matrices() -> &'static [[[f64; 3]; 3]; 4] {
    static M: std::sync::OnceLock<[[[f64; 3]; 3]; 4]> = std::sync::OnceLock::new();
    M.get_or_init(|| {
        blue_side_up_goals().map(|g| {
            let gr = rot_rows_23(&g);
            let g1 = [gr[0], gr[1], gr[2]];
            let g2 = [gr[3], gr[4], gr[5]];
            [cross(&g1, &g2), g1, g2]
        })
    })
}

/// Rows 2–3 of `R·Gᵀ` for the blue-side-up goal `G` with the largest `tr(R·Gᵀ)`, where `R`
/// is the rotation whose rows 2–3 are `rows` (row 1 = row 2 × row 3).
pub fn nearest_goal_rows(rows: &[f32; 6]) -> [f32; 6] {
    let r1 = [rows[0] as f64, rows[1] as f64, rows[2] as f64];
    let r2 = [rows[3] as f64, rows[4] as f64, rows[5] as f64];
    let r = [cross(&r1, &r2), r1, r2];
    let dot = |a: &[f64; 3], b: &[f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let mut best: Option<(f64, [f64; 9])> = None;
    for gm in goal_matrices() {
        let trace: f64 = (0..3).map(|i| dot(&r[i], &gm[i])).sum();
        if best.as_ref().is_none_or(|(t, _)| trace > *t) {
            let mut rel = [0.0; 9];
            for i in 0..3 {
                for j in 0..3 {
                    rel[3 * i + j] = dot(&r[i], &gm[j]);
                }
            }
            best = Some((trace, rel));
        }
    }
    let rel = best.expect("four goals").1;
    let mut out = [0.0f32; 6];
    for k in 0..6 {
        out[k] = rel[3 + k] as f32;
    }
    out
}

/// Format tag of expert weight files.
pub const EXPERT_FORMAT: &str = "pir2-ppo-expert-v1";

/// A trained PPO actor used deterministically (see the module docs).
#[derive(Debug, Clone)]
pub struct PpoExpert {
    net: Mlp,
    norm: FrozenNorm,
    log_std: Vec<f32>,
    prev_action: bool,
    squash: Squash,
    orientation: OrientationInput,
    obs_clip: f32,
    last_act: [f32; NU],
    iteration: u64,
    env_steps: u64,
    obs: Vec<f32>,
    normed: Vec<f32>,
    scratch: [Vec<f32>; 2],
}

impl PpoExpert {
    /// An expert from its parts (checked: the network maps [`actor_dim`] to 16).
    pub(crate) fn from_parts(
        net: Mlp,
        norm: FrozenNorm,
        log_std: Vec<f32>,
        prev_action: bool,
        iteration: u64,
        env_steps: u64,
    ) -> Self {
        let d = actor_dim(prev_action);
        assert_eq!(net.input_dim(), d, "PpoExpert: actor input width");
        assert_eq!(net.output_dim(), NU, "PpoExpert: actor output width");
        assert_eq!(norm.mean.len(), d, "PpoExpert: normaliser width");
        Self {
            net,
            norm,
            log_std,
            prev_action,
            squash: Squash::Clamp,
            orientation: OrientationInput::Absolute,
            obs_clip: super::norm::CLIP,
            last_act: [0.0; NU],
            iteration,
            env_steps,
            obs: vec![0.0; d],
            normed: vec![0.0; d],
            scratch: Default::default(),
        }
    }

    /// Load a weights file written by [`save`](Self::save).
    pub fn load(path: &Path) -> Result<Self> {
        let f = TensorReader::open(path)?;
        let format = f.meta("format")?;
        if format != EXPERT_FORMAT {
            return Err(format_err(
                path,
                format!("format {format:?}, expected {EXPERT_FORMAT:?}"),
            ));
        }
        let sizes: Vec<usize> = f
            .meta("sizes")?
            .split(',')
            .map(|s| s.trim().parse())
            .collect::<std::result::Result<_, _>>()
            .map_err(|_| format_err(path, "metadata `sizes` is malformed".into()))?;
        let act = Activation::from_name(f.meta("activation")?)
            .ok_or_else(|| format_err(path, "unknown activation".into()))?;
        let prev_action: bool = f.meta_parse("prev_action")?;
        let d = actor_dim(prev_action);
        if sizes.first() != Some(&d) || sizes.last() != Some(&NU) {
            return Err(format_err(
                path,
                format!("actor sizes {sizes:?} do not map {d} observations to {NU} actions"),
            ));
        }
        let n: usize = sizes.windows(2).map(|w| w[1] * (w[0] + 1)).sum();
        let net = Mlp::from_params(&sizes, act, f.f32("actor", n)?)
            .ok_or_else(|| format_err(path, "actor parameters do not fit the sizes".into()))?;
        let norm = FrozenNorm {
            mean: f.f32("obs_mean", d)?,
            std: f.f32("obs_std", d)?,
        };
        if norm.std.iter().any(|s| !(s.is_finite() && *s > 0.0))
            || net.params.iter().any(|p| !p.is_finite())
        {
            return Err(format_err(path, "non-finite or non-positive values".into()));
        }
        let mut ex = Self::from_parts(
            net,
            norm,
            f.f32("log_std", NU)?,
            prev_action,
            f.meta_parse("iteration")?,
            f.meta_parse("env_steps")?,
        );
        ex.squash = match f.meta_opt("squash") {
            None | Some("clamp") => Squash::Clamp,
            Some("tanh") => Squash::Tanh,
            Some(other) => {
                return Err(format_err(
                    path,
                    format!("metadata `squash` = {other:?}, expected \"clamp\" or \"tanh\""),
                ))
            }
        };
        ex.orientation = match f.meta_opt("orientation") {
            None | Some("absolute") => OrientationInput::Absolute,
            Some("nearest_goal") => OrientationInput::NearestGoal,
            Some(other) => {
                return Err(format_err(
                    path,
                    format!(
                    "metadata `orientation` = {other:?}, expected \"absolute\" or \"nearest_goal\""
                ),
                ))
            }
        };
        ex.obs_clip = match f.meta_opt("obs_clip") {
            None => super::norm::CLIP,
            Some("none") => f32::INFINITY,
            Some(v) => match v.parse::<f32>() {
                Ok(c) if c > 0.0 && c.is_finite() => c,
                _ => {
                    return Err(format_err(
                        path,
                        format!(
                            "metadata `obs_clip` = {v:?}, expected a positive number or \"none\""
                        ),
                    ))
                }
            },
        };
        Ok(ex)
    }

    /// The action squashing.
    pub fn squash(&self) -> Squash {
        self.squash
    }

    /// The cube-orientation input.
    pub fn orientation_input(&self) -> OrientationInput {
        self.orientation
    }

    /// Write the weights file (atomically).
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut w = TensorWriter::default();
        w.f32("actor", &self.net.params);
        w.f32("obs_mean", &self.norm.mean);
        w.f32("obs_std", &self.norm.std);
        w.f32("log_std", &self.log_std);
        w.meta("format", EXPERT_FORMAT);
        let sizes: Vec<String> = self.net.sizes().iter().map(|s| s.to_string()).collect();
        w.meta("sizes", sizes.join(","));
        w.meta("activation", self.net.activation().name());
        w.meta("prev_action", self.prev_action);
        w.meta("iteration", self.iteration);
        w.meta("env_steps", self.env_steps);
        w.meta("squash", self.squash.name());
        w.meta("orientation", self.orientation.name());
        if self.obs_clip.is_finite() {
            w.meta("obs_clip", self.obs_clip);
        } else {
            w.meta("obs_clip", "none");
        }
        w.write(path)
    }

    /// Whether the observation ends with the previous action.
    pub fn uses_prev_action(&self) -> bool {
        self.prev_action
    }

    /// PPO iteration and environment steps of the weights.
    pub fn trained(&self) -> (u64, u64) {
        (self.iteration, self.env_steps)
    }

    /// Forget the previous action (call at the start of every episode).
    pub fn reset(&mut self) {
        self.last_act = [0.0; NU];
    }

    /// The action for the paper's observation (`fast` 32, `slow` 9): the policy mean,
    /// clamped to `[−1, 1]`. With `prev_action`, the previous output is appended to the
    /// observation, so call [`reset`](Self::reset) at episode starts.
    pub fn act(&mut self, fast: &[f32], slow: &[f32]) -> [f32; NU] {
        assert_eq!(
            fast.len() + slow.len(),
            BASE_OBS_DIM,
            "PpoExpert::act: widths"
        );
        self.obs[..fast.len()].copy_from_slice(fast);
        self.obs[fast.len()..BASE_OBS_DIM].copy_from_slice(slow);
        if self.orientation == OrientationInput::NearestGoal {
            let rows: [f32; 6] = self.obs[35..41].try_into().expect("6 orientation values");
            self.obs[35..41].copy_from_slice(&nearest_goal_rows(&rows));
        }
        if self.prev_action {
            self.obs[BASE_OBS_DIM..].copy_from_slice(&self.last_act);
        }
        self.norm
            .apply_clipped(&self.obs, &mut self.normed, self.obs_clip);
        // The portable path: demonstrations must not depend on the machine's SIMD kernels.
        let mu = self.net.forward_portable(&self.normed, &mut self.scratch);
        let mut a = [0.0f32; NU];
        for i in 0..NU {
            a[i] = match self.squash {
                Squash::Clamp => mu[i].clamp(-1.0, 1.0),
                Squash::Tanh => mu[i].tanh(),
            };
        }
        self.last_act = a;
        a
    }
}

/// Result of [`evaluate`].
#[derive(Debug, Clone, PartialEq)]
pub struct EvalReport {
    /// Episodes run.
    pub episodes: usize,
    /// Episodes that reached a goal.
    pub successes: usize,
    /// Steps to success of the successful episodes, in episode order.
    pub success_steps: Vec<usize>,
    /// Episodes that ended with the cube dropped.
    pub drops: usize,
}

impl EvalReport {
    /// Success rate.
    pub fn success_rate(&self) -> f64 {
        self.successes as f64 / self.episodes.max(1) as f64
    }

    /// Median steps to success (`None` without successes).
    pub fn median_steps(&self) -> Option<usize> {
        let mut s = self.success_steps.clone();
        s.sort_unstable();
        s.get(s.len() / 2).copied()
    }
}

/// Run the deterministic expert on the paper's environment for the episodes with indices
/// in `episodes` (environment seed of episode `i`: [`episode_seeds`]`(seed, i).0`, as the
/// demonstration collector uses), on `threads` threads (the result does not depend on it).
pub fn evaluate(
    model: &LeapModel,
    expert: &PpoExpert,
    episodes: Range<usize>,
    seed: u64,
    threads: usize,
) -> Result<EvalReport> {
    evaluate_delayed(model, expert, episodes, seed, threads, 0)
}

/// [`evaluate`] with the expert's actions reaching the hand `delay` control ticks late: the
/// action computed on the observation of tick `t` is applied at tick `t + delay`, and the
/// first `delay` ticks apply the zero action (hold the motor targets). How much a delay
/// alone costs this task under this expert, with no learning in the way (`delay` 0 is
/// [`evaluate`]).
pub fn evaluate_delayed(
    model: &LeapModel,
    expert: &PpoExpert,
    episodes: Range<usize>,
    seed: u64,
    threads: usize,
    delay: usize,
) -> Result<EvalReport> {
    let idx: Vec<usize> = episodes.collect();
    let threads = threads.clamp(1, idx.len().max(1));
    let run = |mine: Vec<usize>| -> Result<Vec<(usize, bool, bool, usize)>> {
        let cfg = LeapConfig::paper();
        let mut env = LeapCubeEnv::new(model, cfg)?;
        let mut ex = expert.clone();
        let (mut fast, mut slow) = ([0.0f32; 32], [0.0f32; 9]);
        let mut out = Vec::with_capacity(mine.len());
        let mut queue = std::collections::VecDeque::with_capacity(delay + 1);
        for i in mine {
            env.reset(episode_seeds(seed, i).0);
            ex.reset();
            queue.clear();
            queue.extend(std::iter::repeat_n([0.0f32; NU], delay));
            let (mut success, mut steps) = (false, 0);
            for _ in 0..cfg.max_steps {
                env.observe(&mut fast, &mut slow);
                queue.push_back(ex.act(&fast, &slow));
                let a = queue.pop_front().expect("one action queued per tick");
                let st = env.step(&a);
                steps += 1;
                if st.done {
                    success = st.success;
                    break;
                }
            }
            let dropped = !success && steps < cfg.max_steps;
            out.push((i, success, dropped, steps));
        }
        Ok(out)
    };
    let mut parts: Vec<Vec<usize>> = vec![Vec::new(); threads];
    for (k, i) in idx.iter().enumerate() {
        parts[k % threads].push(*i);
    }
    let mut results: Vec<(usize, bool, bool, usize)> = if threads == 1 {
        run(parts.pop().unwrap_or_default())?
    } else {
        let run = &run;
        std::thread::scope(|s| {
            let hs: Vec<_> = parts.into_iter().map(|p| s.spawn(move || run(p))).collect();
            let mut all = Vec::new();
            for h in hs {
                all.extend(h.join().expect("evaluation thread panicked")?);
            }
            Ok::<_, crate::Error>(all)
        })?
    };
    results.sort_by_key(|r| r.0);
    Ok(EvalReport {
        episodes: results.len(),
        successes: results.iter().filter(|r| r.1).count(),
        success_steps: results.iter().filter(|r| r.1).map(|r| r.3).collect(),
        drops: results.iter().filter(|r| r.2).count(),
    })
}
