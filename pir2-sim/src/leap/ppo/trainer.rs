//! The PPO trainer: batched environments, rollouts, GAE, clipped-surrogate updates,
//! observation normalisation, checkpoints.
//!
//! One file on purpose: rollout, GAE, the clipped-surrogate update and the checkpoint share
//! the rollout buffers and one state whose exact order makes resumption bit-identical.
//!
//! # One iteration
//! 1. **Rollout.** `n_envs` environments, `rollout_len` steps each, with the Gaussian
//!    policy `a ~ N(μ(x̂), σ²)` (`x̂` = normalised actor observation, `σ` state-independent);
//!    the environment applies `clamp(a, −1, 1)`. Episodes auto-reset. Environments are
//!    processed in fixed chunks of `env_chunk` (one actor forward per chunk and step), the
//!    chunks spread over the threads.
//! 2. **Advantages.** Critic values of every state (privileged observation), GAE(γ, λ)
//!    with the value of the state after the rollout as bootstrap; a time limit bootstraps
//!    with the value of the final state, success and drop are terminal.
//! 3. **Update.** `epochs` passes over the batch in `minibatches` shuffled minibatches:
//!    clipped surrogate (ε) with advantages normalised over the batch, entropy bonus, value
//!    loss `½(V − R)²`, per-network global gradient-norm clipping, Adam. Each minibatch's
//!    gradient is the ordered sum of `grad_chunks` fixed sub-batches computed in parallel.
//! 4. **Normalisers** (running mean/variance of actor and critic observations) absorb the
//!    rollout's observations — after the update, so the update sees the same normalisation
//!    the rollout acted with.
//!
//! # Determinism and resume
//! Every random draw derives from `seed` and a counter: action noise from the iteration and
//! the environment index, environment resets from the segment, the environment index and
//! the episode count within the segment, minibatch shuffles from the iteration. Work is cut
//! into fixed chunks whose results are combined in a fixed order, so **the result does not
//! depend on the thread count**. Training is divided into segments of `segment_iters`
//! iterations; every environment is reset at the start of a segment (episodes still
//! running at a segment's end are cut like a time limit: bootstrapped, not counted), and
//! checkpoints are taken only at segment boundaries. A checkpoint therefore holds the whole
//! state (weights, Adam moments, normalisers, counters), and a resumed run continues
//! bit-identically to an uninterrupted one.

use std::path::Path;

use pir2_schedule::Rng;
use serde::{Deserialize, Serialize};

use crate::leap::{LeapConfig, LeapModel, NU};

use super::algo::{self, Cut};
use super::expert::PpoExpert;
use super::io::{format_err, TensorReader, TensorWriter};
use super::mlp::{clip_global_norm, Activation, Adam, Mlp, MlpCache};
use super::norm::{FrozenNorm, RunningNorm};
use super::task::{actor_dim, critic_dim, Ending, PpoEnv, RewardTerms};
use crate::error::{Error, Result};

/// Format tag of checkpoint files.
pub const CHECKPOINT_FORMAT: &str = "pir2-ppo-checkpoint-v1";

const SALT_ACT: u64 = 0xA11C_E5ED_0000_0001;
const SALT_ENV: u64 = 0xE0F1_5EED_0000_0002;
const SALT_SHUFFLE: u64 = 0x5B0F_F1E5_0000_0003;
const SALT_INIT: u64 = 0x1A17_0000_0000_0004;

/// Hyper-parameters (all of them change the result; the thread count does not).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PpoConfig {
    /// Seed of everything random.
    pub seed: u64,
    /// Parallel environments.
    pub n_envs: usize,
    /// Steps per environment per iteration.
    pub rollout_len: usize,
    /// Environments per work chunk (divides `n_envs`).
    pub env_chunk: usize,
    /// Iterations per segment (environments reset at segment starts; checkpoint points).
    pub segment_iters: usize,
    /// Passes over each batch.
    pub epochs: usize,
    /// Minibatches per pass (divides `n_envs · rollout_len`).
    pub minibatches: usize,
    /// Sub-batches per minibatch gradient (divides the minibatch size).
    pub grad_chunks: usize,
    /// Discount per control step.
    pub gamma: f32,
    /// GAE λ.
    pub gae_lambda: f32,
    /// Surrogate clip ε.
    pub clip_eps: f32,
    /// Entropy bonus coefficient.
    pub entropy_coef: f32,
    /// Adam learning rate (both networks).
    pub learning_rate: f32,
    /// Global gradient-norm bound per network.
    pub max_grad_norm: f32,
    /// Initial `log σ` of the policy.
    pub init_log_std: f32,
    /// Actor hidden widths.
    pub actor_hidden: Vec<usize>,
    /// Critic hidden widths.
    pub critic_hidden: Vec<usize>,
    /// Hidden activation (`silu` or `tanh`).
    pub activation: String,
    /// Append the previous action to the actor observation.
    pub prev_action: bool,
}

impl Default for PpoConfig {
    /// The CPU recipe: the playground's PPO settings (lr 3e-4, 4 epochs, γ 0.99, λ 0.95,
    /// swish, asymmetric critic) scaled from 8192 to 128 environments, with 256-128-64
    /// networks, entropy 1e-3 and initial σ 0.25 (see the module docs of [`super`]).
    fn default() -> Self {
        Self {
            seed: 0,
            n_envs: 128,
            rollout_len: 64,
            env_chunk: 16,
            segment_iters: 20,
            epochs: 4,
            minibatches: 4,
            grad_chunks: 8,
            gamma: 0.99,
            gae_lambda: 0.95,
            clip_eps: 0.2,
            entropy_coef: 1e-3,
            learning_rate: 3e-4,
            max_grad_norm: 1.0,
            init_log_std: (0.25f32).ln(),
            actor_hidden: vec![256, 128, 64],
            critic_hidden: vec![256, 128, 64],
            activation: "silu".into(),
            prev_action: false,
        }
    }
}

impl PpoConfig {
    /// Check divisibility and ranges.
    pub fn validate(&self) -> Result<()> {
        let batch = self.n_envs * self.rollout_len;
        let bad = |m: String| Err(Error::PpoInvalid(m));
        if self.n_envs == 0 || self.rollout_len == 0 || self.env_chunk == 0 {
            return bad("n_envs, rollout_len and env_chunk must be positive".into());
        }
        if self.n_envs % self.env_chunk != 0 {
            return bad(format!(
                "env_chunk {} does not divide n_envs {}",
                self.env_chunk, self.n_envs
            ));
        }
        if self.minibatches == 0 || batch % self.minibatches != 0 {
            return bad(format!(
                "minibatches {} does not divide the batch {batch}",
                self.minibatches
            ));
        }
        let mb = batch / self.minibatches;
        if self.grad_chunks == 0 || mb % self.grad_chunks != 0 {
            return bad(format!(
                "grad_chunks {} does not divide the minibatch {mb}",
                self.grad_chunks
            ));
        }
        if self.segment_iters == 0 || self.epochs == 0 {
            return bad("segment_iters and epochs must be positive".into());
        }
        if Activation::from_name(&self.activation).is_none() {
            return bad(format!("unknown activation {:?}", self.activation));
        }
        let unit = |x: f32| (0.0..=1.0).contains(&x);
        if !(unit(self.gamma) && unit(self.gae_lambda) && self.clip_eps > 0.0) {
            return bad("gamma and gae_lambda must lie in [0, 1], clip_eps > 0".into());
        }
        if !(self.learning_rate > 0.0 && self.max_grad_norm > 0.0 && self.entropy_coef >= 0.0) {
            return bad("learning_rate, max_grad_norm > 0 and entropy_coef ≥ 0".into());
        }
        Ok(())
    }

    fn act(&self) -> Activation {
        Activation::from_name(&self.activation).unwrap_or(Activation::Silu)
    }

    fn sizes(&self, input: usize, hidden: &[usize], out: usize) -> Vec<usize> {
        let mut s = vec![input];
        s.extend_from_slice(hidden);
        s.push(out);
        s
    }
}

/// One finished episode (training rollouts).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EpisodeRecord {
    /// Reached a goal.
    pub success: bool,
    /// The cube dropped.
    pub dropped: bool,
    /// Control steps.
    pub len: usize,
    /// Undiscounted return.
    pub ret: f64,
    /// Reward terms summed over the episode.
    pub terms: RewardTerms,
}

/// What one iteration did.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct IterStats {
    /// Iteration index (0-based) just completed.
    pub iteration: u64,
    /// Environment steps after it.
    pub env_steps: u64,
    /// Episodes finished during the rollout (in environment order).
    pub episodes: Vec<EpisodeRecord>,
    /// Mean reward per step in the rollout.
    pub mean_step_reward: f64,
    /// Mean clipped-surrogate loss.
    pub policy_loss: f64,
    /// Mean value loss `½(V − R)²`.
    pub value_loss: f64,
    /// Fraction of clipped rows.
    pub clip_frac: f64,
    /// Mean approximate KL(old ‖ new).
    pub approx_kl: f64,
    /// Mean policy σ after the update.
    pub mean_std: f64,
    /// Fraction of the variance of the returns the values explain (before the update).
    pub explained_variance: f64,
    /// Seconds spent in rollouts (physics + acting + values).
    pub rollout_secs: f64,
    /// Seconds spent in the update.
    pub learn_secs: f64,
}

/// Per-environment rollout storage (rows in time order).
#[derive(Debug, Clone, Default)]
struct EnvBuf {
    obs_a: Vec<f32>,
    obs_c: Vec<f32>,
    act: Vec<f32>,
    logp: Vec<f32>,
    rew: Vec<f32>,
    val: Vec<f32>,
    adv: Vec<f32>,
    ret: Vec<f32>,
}

#[derive(Debug, Clone, Copy, Default)]
struct Slot {
    episode: u64,
    ret: f64,
    terms: RewardTerms,
}

/// Per-sub-batch scratch for gradients.
#[derive(Debug, Default)]
struct GradWs {
    xa: Vec<f32>,
    xc: Vec<f32>,
    act: Vec<f32>,
    logp: Vec<f32>,
    adv: Vec<f32>,
    ret: Vec<f32>,
    d_mu: Vec<f32>,
    d_v: Vec<f32>,
    g_actor: Vec<f32>,
    g_std: Vec<f32>,
    g_critic: Vec<f32>,
    ca: MlpCache,
    cc: MlpCache,
    surrogate: algo::SurrogateStats,
    value_loss: f64,
}

/// Run `f` on every item, spreading the items over `threads` threads round-robin;
/// results in item order.
fn par_map<T: Send, R: Send>(items: Vec<T>, threads: usize, f: impl Fn(T) -> R + Sync) -> Vec<R> {
    if threads <= 1 || items.len() <= 1 {
        return items.into_iter().map(f).collect();
    }
    let n = items.len();
    let mut lists: Vec<Vec<(usize, T)>> = (0..threads.min(n)).map(|_| Vec::new()).collect();
    let k = lists.len();
    for (i, it) in items.into_iter().enumerate() {
        lists[i % k].push((i, it));
    }
    let f = &f;
    let mut out: Vec<(usize, R)> = std::thread::scope(|s| {
        let mut first = lists.remove(0);
        let hs: Vec<_> = lists
            .into_iter()
            .map(|l| s.spawn(move || l.into_iter().map(|(i, t)| (i, f(t))).collect::<Vec<_>>()))
            .collect();
        let mut all: Vec<(usize, R)> = first.drain(..).map(|(i, t)| (i, f(t))).collect();
        for h in hs {
            all.extend(h.join().expect("PPO worker thread panicked"));
        }
        all
    });
    out.sort_by_key(|p| p.0);
    out.into_iter().map(|p| p.1).collect()
}

/// Read-only inputs of a rollout chunk.
struct RolloutCtx<'a> {
    cfg: &'a PpoConfig,
    actor: &'a Mlp,
    log_std: &'a [f32],
    critic: &'a Mlp,
    na: &'a FrozenNorm,
    nc: &'a FrozenNorm,
    act_seed: u64,
    env_seed: u64,
}

/// Reset seed of episode `episode` (< 2³²) of environment `env` in a segment.
fn reset_seed(env_seed: u64, env: usize, episode: u64) -> u64 {
    debug_assert!(episode < 1 << 32);
    Rng::derive(env_seed, ((env as u64) << 32) | (episode & 0xFFFF_FFFF)).next_u64()
}

/// Roll one chunk of environments (global indices from `first`) and compute its values and
/// advantages; returns the episodes finished, in (environment, time) order.
fn rollout_chunk(
    cx: &RolloutCtx<'_>,
    first: usize,
    envs: &mut [PpoEnv],
    slots: &mut [Slot],
    bufs: &mut [EnvBuf],
) -> Vec<(usize, usize, EpisodeRecord)> {
    let cfg = cx.cfg;
    let (c, t_len) = (envs.len(), cfg.rollout_len);
    let (da, dc) = (actor_dim(cfg.prev_action), critic_dim(cfg.prev_action));
    let mut rngs: Vec<Rng> = (0..c)
        .map(|k| Rng::derive(cx.act_seed, (first + k) as u64))
        .collect();
    let mut xa = vec![0.0f32; c * da];
    let mut xan = vec![0.0f32; c * da];
    let mut cache = MlpCache::default();
    let std: Vec<f32> = cx.log_std.iter().map(|l| l.exp()).collect();
    let mut cuts = vec![vec![Cut::No; t_len]; c];
    let mut next_v = vec![vec![f32::NAN; t_len]; c];
    // (env, t, critic obs of the final state) for time limits.
    let mut trunc: Vec<(usize, usize, Vec<f32>)> = Vec::new();
    let mut finished = Vec::new();
    for b in bufs.iter_mut() {
        b.obs_a.resize(t_len * da, 0.0);
        b.obs_c.resize(t_len * dc, 0.0);
        b.act.resize(t_len * NU, 0.0);
        b.logp.resize(t_len, 0.0);
        b.rew.resize(t_len, 0.0);
    }
    for t in 0..t_len {
        for k in 0..c {
            envs[k].actor_obs(&mut xa[k * da..(k + 1) * da]);
            bufs[k].obs_a[t * da..(t + 1) * da].copy_from_slice(&xa[k * da..(k + 1) * da]);
            envs[k].critic_obs(&mut bufs[k].obs_c[t * dc..(t + 1) * dc]);
        }
        cx.na.apply(&xa, &mut xan);
        let mu = cx.actor.forward(&xan, c, &mut cache);
        for k in 0..c {
            let b = &mut bufs[k];
            let a = &mut b.act[t * NU..(t + 1) * NU];
            for j in 0..NU {
                a[j] = mu[k * NU + j] + std[j] * rngs[k].normal();
            }
            b.logp[t] = algo::log_prob(&mu[k * NU..(k + 1) * NU], cx.log_std, a);
            let out = envs[k].step(a);
            b.rew[t] = out.reward;
            let s = &mut slots[k];
            s.ret += f64::from(out.reward);
            s.terms.add(&out.terms);
            match out.ending {
                Ending::Running => {}
                Ending::Success | Ending::Dropped => {
                    cuts[k][t] = Cut::Yes;
                    next_v[k][t] = 0.0;
                }
                Ending::TimeLimit => {
                    cuts[k][t] = Cut::Yes;
                    let mut o = vec![0.0; dc];
                    envs[k].critic_obs(&mut o);
                    trunc.push((k, t, o));
                }
            }
            if out.ending != Ending::Running {
                finished.push((
                    k,
                    t,
                    EpisodeRecord {
                        success: out.ending == Ending::Success,
                        dropped: out.ending == Ending::Dropped,
                        len: out.steps,
                        ret: s.ret,
                        terms: s.terms,
                    },
                ));
                let seed = reset_seed(cx.env_seed, first + k, s.episode);
                s.episode += 1;
                s.ret = 0.0;
                s.terms = RewardTerms::default();
                envs[k].reset(seed);
            }
        }
    }
    // Values: every stored state, the state after the rollout, the final states of
    // time limits.
    let mut rows = Vec::with_capacity(c * t_len * dc + (c + trunc.len()) * dc);
    for b in bufs.iter() {
        rows.extend_from_slice(&b.obs_c);
    }
    let mut o = vec![0.0; dc];
    for e in envs.iter() {
        e.critic_obs(&mut o);
        rows.extend_from_slice(&o);
    }
    for (_, _, o) in &trunc {
        rows.extend_from_slice(o);
    }
    let n_rows = rows.len() / dc;
    let mut normed = vec![0.0; rows.len()];
    cx.nc.apply(&rows, &mut normed);
    let v = cx.critic.forward(&normed, n_rows, &mut cache).to_vec();
    for (i, (k, t, _)) in trunc.iter().enumerate() {
        next_v[*k][*t] = v[c * t_len + c + i];
    }
    for k in 0..c {
        let b = &mut bufs[k];
        b.val.clear();
        b.val.extend_from_slice(&v[k * t_len..(k + 1) * t_len]);
        for t in 0..t_len {
            if cuts[k][t] == Cut::No {
                next_v[k][t] = if t + 1 < t_len {
                    b.val[t + 1]
                } else {
                    v[c * t_len + k]
                };
            }
        }
        b.adv.resize(t_len, 0.0);
        algo::gae(
            &b.rew,
            &b.val,
            &next_v[k],
            &cuts[k],
            cfg.gamma,
            cfg.gae_lambda,
            &mut b.adv,
        );
        b.ret.clear();
        b.ret.extend(b.adv.iter().zip(&b.val).map(|(a, v)| a + v));
    }
    finished
        .into_iter()
        .map(|(k, t, r)| (first + k, t, r))
        .collect()
}

/// The PPO trainer (see the module docs).
#[derive(Debug)]
pub struct Trainer {
    cfg: PpoConfig,
    threads: usize,
    actor: Mlp,
    log_std: Vec<f32>,
    critic: Mlp,
    opt_actor: Adam,
    opt_std: Adam,
    opt_critic: Adam,
    norm_a: RunningNorm,
    norm_c: RunningNorm,
    iteration: u64,
    env_steps: u64,
    envs: Vec<PpoEnv>,
    slots: Vec<Slot>,
    bufs: Vec<EnvBuf>,
    ws: Vec<GradWs>,
}

impl Trainer {
    /// A fresh trainer (networks initialised from `cfg.seed`) on `model`, running its
    /// environments and gradients on `threads` threads.
    pub fn new(model: &LeapModel, cfg: PpoConfig, threads: usize) -> Result<Self> {
        cfg.validate()?;
        let (da, dc) = (actor_dim(cfg.prev_action), critic_dim(cfg.prev_action));
        let mut rng = Rng::derive(cfg.seed, SALT_INIT);
        let act = cfg.act();
        // Small output layer for the actor (actions start near 0), unit gain for the critic.
        let actor = Mlp::new(&cfg.sizes(da, &cfg.actor_hidden, NU), act, 0.01, &mut rng);
        let critic = Mlp::new(&cfg.sizes(dc, &cfg.critic_hidden, 1), act, 1.0, &mut rng);
        let envs = (0..cfg.n_envs)
            .map(|_| PpoEnv::new(model, LeapConfig::paper(), cfg.prev_action))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            opt_actor: Adam::new(actor.params.len()),
            opt_std: Adam::new(NU),
            opt_critic: Adam::new(critic.params.len()),
            log_std: vec![cfg.init_log_std; NU],
            actor,
            critic,
            norm_a: RunningNorm::new(da),
            norm_c: RunningNorm::new(dc),
            iteration: 0,
            env_steps: 0,
            slots: vec![Slot::default(); cfg.n_envs],
            bufs: vec![EnvBuf::default(); cfg.n_envs],
            ws: (0..cfg.grad_chunks).map(|_| GradWs::default()).collect(),
            envs,
            threads: threads.max(1),
            cfg,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &PpoConfig {
        &self.cfg
    }

    /// Iterations completed.
    pub fn iteration(&self) -> u64 {
        self.iteration
    }

    /// Environment steps taken.
    pub fn env_steps(&self) -> u64 {
        self.env_steps
    }

    /// True when the next iteration starts a segment (a checkpoint may be taken now).
    pub fn at_segment_boundary(&self) -> bool {
        self.iteration % self.cfg.segment_iters as u64 == 0
    }

    /// The training environments (read-only; for tests and diagnostics).
    pub fn envs(&self) -> &[PpoEnv] {
        &self.envs
    }

    /// Change the thread count (does not change results).
    pub fn set_threads(&mut self, threads: usize) {
        self.threads = threads.max(1);
    }

    /// The current deterministic expert (actor + frozen normaliser).
    pub fn expert(&self) -> PpoExpert {
        PpoExpert::from_parts(
            self.actor.clone(),
            self.norm_a.frozen(),
            self.log_std.clone(),
            self.cfg.prev_action,
            self.iteration,
            self.env_steps,
        )
    }

    /// One PPO iteration (rollout, advantages, update, normaliser update).
    pub fn iterate(&mut self) -> Result<IterStats> {
        let cfg = self.cfg.clone();
        let it = self.iteration;
        let segment = it / cfg.segment_iters as u64;
        let env_seed = Rng::derive(cfg.seed ^ SALT_ENV, segment).next_u64();
        if self.at_segment_boundary() {
            // Episode 0 of every environment starts here; later resets count from 1.
            for (i, (e, s)) in self.envs.iter_mut().zip(&mut self.slots).enumerate() {
                *s = Slot {
                    episode: 1,
                    ..Slot::default()
                };
                e.reset(reset_seed(env_seed, i, 0));
            }
        }
        let t0 = std::time::Instant::now();
        let (na, nc) = (self.norm_a.frozen(), self.norm_c.frozen());
        let cx = RolloutCtx {
            cfg: &cfg,
            actor: &self.actor,
            log_std: &self.log_std,
            critic: &self.critic,
            na: &na,
            nc: &nc,
            act_seed: Rng::derive(cfg.seed ^ SALT_ACT, it).next_u64(),
            env_seed,
        };
        let ch = cfg.env_chunk;
        let items: Vec<_> = self
            .envs
            .chunks_mut(ch)
            .zip(self.slots.chunks_mut(ch))
            .zip(self.bufs.chunks_mut(ch))
            .enumerate()
            .collect();
        let per_chunk = par_map(items, self.threads, |(i, ((e, s), b))| {
            rollout_chunk(&cx, i * ch, e, s, b)
        });
        let episodes: Vec<EpisodeRecord> = per_chunk.into_iter().flatten().map(|r| r.2).collect();
        let rollout_secs = t0.elapsed().as_secs_f64();
        let t1 = std::time::Instant::now();
        let mut stats = self.update(&na, &nc)?;
        // Normalisers absorb this rollout (environment order, then time).
        for b in &self.bufs {
            self.norm_a.update(&b.obs_a);
            self.norm_c.update(&b.obs_c);
        }
        self.iteration += 1;
        self.env_steps += (cfg.n_envs * cfg.rollout_len) as u64;
        let n = (cfg.n_envs * cfg.rollout_len) as f64;
        stats.iteration = it;
        stats.env_steps = self.env_steps;
        stats.mean_step_reward = self
            .bufs
            .iter()
            .flat_map(|b| b.rew.iter())
            .map(|&r| f64::from(r))
            .sum::<f64>()
            / n;
        stats.episodes = episodes;
        stats.rollout_secs = rollout_secs;
        stats.learn_secs = t1.elapsed().as_secs_f64();
        Ok(stats)
    }

    fn update(&mut self, na: &FrozenNorm, nc: &FrozenNorm) -> Result<IterStats> {
        let cfg = &self.cfg;
        let (da, dc) = (actor_dim(cfg.prev_action), critic_dim(cfg.prev_action));
        let t_len = cfg.rollout_len;
        let batch = cfg.n_envs * t_len;
        // Advantage normalisation over the whole batch; explained variance.
        let (mut s, mut s2) = (0.0f64, 0.0f64);
        for b in &self.bufs {
            for &a in &b.adv {
                s += f64::from(a);
                s2 += f64::from(a) * f64::from(a);
            }
        }
        let mean = s / batch as f64;
        let std = (s2 / batch as f64 - mean * mean).max(0.0).sqrt();
        let (adv_mean, adv_inv) = (mean as f32, (1.0 / (std + 1e-8)) as f32);
        let ev = {
            let (mut sr, mut sr2, mut se2) = (0.0f64, 0.0f64, 0.0f64);
            for b in &self.bufs {
                for (r, v) in b.ret.iter().zip(&b.val) {
                    let r = f64::from(*r);
                    sr += r;
                    sr2 += r * r;
                    se2 += (r - f64::from(*v)).powi(2);
                }
            }
            let var = sr2 / batch as f64 - (sr / batch as f64).powi(2);
            if var > 0.0 {
                1.0 - se2 / batch as f64 / var
            } else {
                f64::NAN
            }
        };
        let mb = batch / cfg.minibatches;
        let sub = mb / cfg.grad_chunks;
        let mut shuffle = Rng::derive(cfg.seed ^ SALT_SHUFFLE, self.iteration);
        let mut perm: Vec<u32> = (0..batch as u32).collect();
        let mut g_actor = vec![0.0f32; self.actor.params.len()];
        let mut g_std = vec![0.0f32; NU];
        let mut g_critic = vec![0.0f32; self.critic.params.len()];
        let mut st = IterStats::default();
        let (mut n_rows, mut n_steps) = (0.0f64, 0.0f64);
        for _epoch in 0..cfg.epochs {
            for i in (1..batch).rev() {
                let j = shuffle.below(i as u64 + 1) as usize;
                perm.swap(i, j);
            }
            for m in 0..cfg.minibatches {
                let idx = &perm[m * mb..(m + 1) * mb];
                let (actor, critic, log_std, bufs) =
                    (&self.actor, &self.critic, &self.log_std, &self.bufs);
                let items: Vec<(usize, &mut GradWs)> = self.ws.iter_mut().enumerate().collect();
                let scale = 1.0 / mb as f32;
                par_map(items, self.threads, |(c, ws)| {
                    let rows = &idx[c * sub..(c + 1) * sub];
                    ws.xa.resize(sub * da, 0.0);
                    ws.xc.resize(sub * dc, 0.0);
                    ws.act.resize(sub * NU, 0.0);
                    ws.logp.resize(sub, 0.0);
                    ws.adv.resize(sub, 0.0);
                    ws.ret.resize(sub, 0.0);
                    for (r, &g) in rows.iter().enumerate() {
                        let (e, t) = (g as usize / t_len, g as usize % t_len);
                        let b = &bufs[e];
                        na.apply(
                            &b.obs_a[t * da..(t + 1) * da],
                            &mut ws.xa[r * da..(r + 1) * da],
                        );
                        nc.apply(
                            &b.obs_c[t * dc..(t + 1) * dc],
                            &mut ws.xc[r * dc..(r + 1) * dc],
                        );
                        ws.act[r * NU..(r + 1) * NU].copy_from_slice(&b.act[t * NU..(t + 1) * NU]);
                        ws.logp[r] = b.logp[t];
                        ws.adv[r] = (b.adv[t] - adv_mean) * adv_inv;
                        ws.ret[r] = b.ret[t];
                    }
                    // Actor.
                    let mu = actor.forward(&ws.xa, sub, &mut ws.ca);
                    ws.d_mu.resize(sub * NU, 0.0);
                    ws.g_std.clear();
                    ws.g_std.resize(NU, 0.0);
                    ws.surrogate = algo::surrogate_grad(
                        mu,
                        log_std,
                        &ws.act,
                        &ws.logp,
                        &ws.adv,
                        cfg.clip_eps,
                        scale,
                        &mut ws.d_mu,
                        &mut ws.g_std,
                    );
                    ws.g_actor.clear();
                    ws.g_actor.resize(actor.params.len(), 0.0);
                    actor.backward(&mut ws.ca, &ws.d_mu, &mut ws.g_actor);
                    // Critic.
                    let v = critic.forward(&ws.xc, sub, &mut ws.cc);
                    ws.d_v.resize(sub, 0.0);
                    ws.value_loss = 0.0;
                    for r in 0..sub {
                        let e = v[r] - ws.ret[r];
                        ws.value_loss += 0.5 * f64::from(e) * f64::from(e);
                        ws.d_v[r] = e * scale;
                    }
                    ws.g_critic.clear();
                    ws.g_critic.resize(critic.params.len(), 0.0);
                    critic.backward(&mut ws.cc, &ws.d_v, &mut ws.g_critic);
                });
                g_actor.fill(0.0);
                g_std.fill(0.0);
                g_critic.fill(0.0);
                for ws in &self.ws {
                    for (g, w) in g_actor.iter_mut().zip(&ws.g_actor) {
                        *g += w;
                    }
                    for (g, w) in g_std.iter_mut().zip(&ws.g_std) {
                        *g += w;
                    }
                    for (g, w) in g_critic.iter_mut().zip(&ws.g_critic) {
                        *g += w;
                    }
                    st.policy_loss += ws.surrogate.loss;
                    st.clip_frac += ws.surrogate.clipped;
                    st.approx_kl += ws.surrogate.approx_kl;
                    st.value_loss += ws.value_loss;
                }
                n_rows += mb as f64;
                n_steps += 1.0;
                // Entropy bonus: ∂(−c·H)/∂log σⱼ = −c.
                g_std.iter_mut().for_each(|g| *g -= cfg.entropy_coef);
                clip_global_norm(&mut [&mut g_actor[..], &mut g_std[..]], cfg.max_grad_norm);
                let gn = clip_global_norm(&mut [&mut g_critic[..]], cfg.max_grad_norm);
                if !gn.is_finite() || g_actor.iter().any(|g| !g.is_finite()) {
                    return Err(Error::PpoDiverged {
                        iteration: self.iteration,
                        what: "gradient",
                    });
                }
                let lr = cfg.learning_rate;
                self.opt_actor.step(&mut self.actor.params, &g_actor, lr);
                self.opt_std.step(&mut self.log_std, &g_std, lr);
                self.opt_critic.step(&mut self.critic.params, &g_critic, lr);
            }
        }
        if self
            .actor
            .params
            .iter()
            .chain(&self.critic.params)
            .chain(&self.log_std)
            .any(|p| !p.is_finite())
        {
            return Err(Error::PpoDiverged {
                iteration: self.iteration,
                what: "parameter",
            });
        }
        let _ = n_steps;
        st.policy_loss /= n_rows;
        st.value_loss /= n_rows;
        st.clip_frac /= n_rows;
        st.approx_kl /= n_rows;
        st.mean_std = self.log_std.iter().map(|l| f64::from(l.exp())).sum::<f64>() / NU as f64;
        st.explained_variance = ev;
        Ok(st)
    }

    /// Write a checkpoint (atomically). Only at a segment boundary (see the module docs).
    pub fn save_checkpoint(&self, path: &Path) -> Result<()> {
        if !self.at_segment_boundary() {
            return Err(Error::PpoInvalid(format!(
                "checkpoints are taken at segment boundaries; iteration {} is inside a segment",
                self.iteration
            )));
        }
        let mut w = TensorWriter::default();
        w.f32("actor", &self.actor.params);
        w.f32("log_std", &self.log_std);
        w.f32("critic", &self.critic.params);
        for (name, opt) in [
            ("actor", &self.opt_actor),
            ("log_std", &self.opt_std),
            ("critic", &self.opt_critic),
        ] {
            w.f32(&format!("adam.{name}.m"), &opt.m);
            w.f32(&format!("adam.{name}.v"), &opt.v);
            w.meta(&format!("adam.{name}.t"), opt.t);
        }
        for (name, n) in [("actor", &self.norm_a), ("critic", &self.norm_c)] {
            w.f64(&format!("norm.{name}.mean"), &n.mean);
            w.f64(&format!("norm.{name}.m2"), &n.m2);
            // Bit pattern, so the count survives exactly.
            w.meta(&format!("norm.{name}.count_bits"), n.count.to_bits());
        }
        w.meta("format", CHECKPOINT_FORMAT);
        w.meta(
            "config",
            serde_json::to_string(&self.cfg).map_err(|e| format_err(path, e.to_string()))?,
        );
        w.meta("iteration", self.iteration);
        w.meta("env_steps", self.env_steps);
        w.write(path)
    }

    /// Restore a trainer from a checkpoint written by [`save_checkpoint`](Self::save_checkpoint).
    pub fn load_checkpoint(model: &LeapModel, path: &Path, threads: usize) -> Result<Self> {
        let f = TensorReader::open(path)?;
        let format = f.meta("format")?;
        if format != CHECKPOINT_FORMAT {
            return Err(format_err(
                path,
                format!("format {format:?}, expected {CHECKPOINT_FORMAT:?}"),
            ));
        }
        let cfg: PpoConfig = serde_json::from_str(f.meta("config")?)
            .map_err(|e| format_err(path, format!("config: {e}")))?;
        let mut tr = Self::new(model, cfg, threads)?;
        tr.actor.params = f.f32("actor", tr.actor.params.len())?;
        tr.log_std = f.f32("log_std", NU)?;
        tr.critic.params = f.f32("critic", tr.critic.params.len())?;
        for (name, opt) in [
            ("actor", &mut tr.opt_actor),
            ("log_std", &mut tr.opt_std),
            ("critic", &mut tr.opt_critic),
        ] {
            let n = opt.m.len();
            opt.m = f.f32(&format!("adam.{name}.m"), n)?;
            opt.v = f.f32(&format!("adam.{name}.v"), n)?;
            opt.t = f.meta_parse(&format!("adam.{name}.t"))?;
        }
        for (name, nm) in [("actor", &mut tr.norm_a), ("critic", &mut tr.norm_c)] {
            let d = nm.dim();
            nm.mean = f.f64(&format!("norm.{name}.mean"), d)?;
            nm.m2 = f.f64(&format!("norm.{name}.m2"), d)?;
            nm.count = f64::from_bits(f.meta_parse(&format!("norm.{name}.count_bits"))?);
        }
        tr.iteration = f.meta_parse("iteration")?;
        tr.env_steps = f.meta_parse("env_steps")?;
        if !tr.at_segment_boundary() {
            return Err(format_err(
                f.path(),
                format!("iteration {} is not a segment boundary", tr.iteration),
            ));
        }
        Ok(tr)
    }

    /// Everything that determines the future of training, for equality tests: weights,
    /// Adam moments and step counts, normalisers and counters.
    pub fn state_fingerprint(&self) -> Vec<u64> {
        let mut h = Vec::new();
        let bits32 = |v: &[f32]| v.iter().map(|x| u64::from(x.to_bits())).collect::<Vec<_>>();
        let bits64 = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let mut mix = |v: Vec<u64>| {
            let mut acc = 0xcbf2_9ce4_8422_2325u64;
            for x in v {
                acc = (acc ^ x).wrapping_mul(0x0100_0000_01b3);
            }
            h.push(acc);
        };
        mix(bits32(&self.actor.params));
        mix(bits32(&self.log_std));
        mix(bits32(&self.critic.params));
        for o in [&self.opt_actor, &self.opt_std, &self.opt_critic] {
            mix(bits32(&o.m));
            mix(bits32(&o.v));
            mix(vec![o.t]);
        }
        for n in [&self.norm_a, &self.norm_c] {
            mix(bits64(&n.mean));
            mix(bits64(&n.m2));
            mix(vec![n.count.to_bits()]);
        }
        mix(vec![self.iteration, self.env_steps]);
        h
    }
}
