//! The trained policy as a deterministic expert: `act(observation) → action`, the clamped
//! mean of the Gaussian policy, and its evaluation on the paper's environment.
//!
//! Weights file (safetensors, format `pir2-ppo-expert-v1`): tensors `actor` (the flat MLP
//! parameters: per layer the `out × in` row-major weight matrix, then the bias), `obs_mean`
//! and `obs_std` (the frozen observation normalisation, `x ↦ clip((x − mean)/std, ±10)`),
//! `log_std` (the exploration noise, informational); metadata `format`, `sizes` (layer
//! widths, comma-separated, input first), `activation` (`silu` or `tanh`), `prev_action`
//! (`true` if the observation ends with the previous action), `iteration`, `env_steps`.

use std::ops::Range;
use std::path::Path;

use pir2_runtime::Environment;

use crate::leap::{episode_seeds, LeapConfig, LeapCubeEnv, LeapModel, NU};

use super::error::Result;
use super::io::{format_err, TensorReader, TensorWriter};
use super::mlp::{Activation, Mlp, MlpCache};
use super::norm::FrozenNorm;
use super::task::{actor_dim, BASE_OBS_DIM};

/// Format tag of expert weight files.
pub const EXPERT_FORMAT: &str = "pir2-ppo-expert-v1";

/// A trained PPO actor used deterministically (see the module docs).
#[derive(Debug, Clone)]
pub struct PpoExpert {
    net: Mlp,
    norm: FrozenNorm,
    log_std: Vec<f32>,
    prev_action: bool,
    last_act: [f32; NU],
    iteration: u64,
    env_steps: u64,
    obs: Vec<f32>,
    normed: Vec<f32>,
    cache: MlpCache,
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
            last_act: [0.0; NU],
            iteration,
            env_steps,
            obs: vec![0.0; d],
            normed: vec![0.0; d],
            cache: MlpCache::default(),
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
        Ok(Self::from_parts(
            net,
            norm,
            f.f32("log_std", NU)?,
            prev_action,
            f.meta_parse("iteration")?,
            f.meta_parse("env_steps")?,
        ))
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
        if self.prev_action {
            self.obs[BASE_OBS_DIM..].copy_from_slice(&self.last_act);
        }
        self.norm.apply(&self.obs, &mut self.normed);
        let mu = self.net.forward(&self.normed, 1, &mut self.cache);
        let mut a = [0.0f32; NU];
        for i in 0..NU {
            a[i] = mu[i].clamp(-1.0, 1.0);
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
    let idx: Vec<usize> = episodes.collect();
    let threads = threads.clamp(1, idx.len().max(1));
    let run = |mine: Vec<usize>| -> Result<Vec<(usize, bool, bool, usize)>> {
        let cfg = LeapConfig::paper();
        let mut env = LeapCubeEnv::new(model, cfg)?;
        let mut ex = expert.clone();
        let (mut fast, mut slow) = ([0.0f32; 32], [0.0f32; 9]);
        let mut out = Vec::with_capacity(mine.len());
        for i in mine {
            env.reset(episode_seeds(seed, i).0);
            ex.reset();
            let (mut success, mut steps) = (false, 0);
            for _ in 0..cfg.max_steps {
                env.observe(&mut fast, &mut slow);
                let a = ex.act(&fast, &slow);
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
            Ok::<_, super::PpoError>(all)
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
