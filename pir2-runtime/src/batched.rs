//! Lock-step evaluation with batched model calls: the episodes of a study cell run side by
//! side, and the calls they make are answered together, one batched call per round.
//!
//! Every episode keeps the runtime's own [`ActionHead`](crate::ActionHead) and
//! [`LockstepDriver`](crate::LockstepDriver); its head is given a proxy model that hands each
//! call to a shared round and waits for the answer. A
//! round runs when every live episode of the group is either waiting in a call or finished,
//! so round `r` holds the `r`-th call of each episode still running, in episode order. The
//! batch's composition therefore follows from the episodes alone, never from thread timing,
//! and a cell's result is deterministic: the same episodes, group size and model (for a
//! multi-threaded backend, the same kernel thread count) give the same bits.
//!
//! A batched forward need not give the bits of the same rows run one at a time (a backend's
//! kernels may sum in another order at another batch size), so a batched cell is its own
//! measurement: equal in distribution to [`crate::eval_cell`]'s, not bit for bit.
//!
//! Fail closed: an episode that ends with an error or a panic leaves the round at once (its
//! proxy counts it finished when dropped), so the others never wait for it, and the cell ends
//! in that episode's error ([`Error::Panicked`] for a panic); a failed batched call is
//! answered to every waiting episode with the error, and the cell ends in that one error (a
//! panic in the batched call too, as [`Error::Panicked`]).

use std::collections::BTreeMap;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};

use crate::error::{Error, Result};
use crate::io::Environment;
use crate::lockstep::{cell_episode, StudyCell};
use crate::model::{ModelInput, SlowInput, VelocityModel};

/// The slow input's layout without its data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SlowLayout {
    None,
    Vector { dim: usize },
    Tokens { tokens: usize, dim: usize },
}

/// One episode's call, copied out of its head.
#[derive(Debug)]
struct Call {
    batch: usize,
    horizon: usize,
    action_dim: usize,
    n_obs: usize,
    fast_dim: usize,
    slow_layout: SlowLayout,
    x: Vec<f32>,
    tau: Vec<f32>,
    obs_fast: Vec<f32>,
    slow: Vec<f32>,
    d_vis: Vec<u32>,
}

impl Call {
    fn new(input: &ModelInput<'_>) -> Self {
        let (slow_layout, slow) = match input.slow {
            SlowInput::None => (SlowLayout::None, Vec::new()),
            SlowInput::Vector { data, dim } => (SlowLayout::Vector { dim }, data.to_vec()),
            SlowInput::Tokens { data, tokens, dim } => {
                (SlowLayout::Tokens { tokens, dim }, data.to_vec())
            }
        };
        Self {
            batch: input.batch,
            horizon: input.horizon,
            action_dim: input.action_dim,
            n_obs: input.n_obs,
            fast_dim: input.fast_dim,
            slow_layout,
            x: input.x.to_vec(),
            tau: input.tau.to_vec(),
            obs_fast: input.obs_fast.to_vec(),
            slow,
            d_vis: input.d_vis.to_vec(),
        }
    }

    /// Whether `other` can share a batched call with `self`.
    fn same_layout(&self, other: &Call) -> bool {
        (
            self.horizon,
            self.action_dim,
            self.n_obs,
            self.fast_dim,
            self.slow_layout,
        ) == (
            other.horizon,
            other.action_dim,
            other.n_obs,
            other.fast_dim,
            other.slow_layout,
        )
    }
}

/// The state of the current round.
#[derive(Debug, Default)]
struct Round {
    /// Episodes whose proxy is still alive.
    live: usize,
    /// Calls submitted and not yet run, by episode.
    calls: BTreeMap<usize, Call>,
    /// Answers not yet collected, by episode.
    answers: BTreeMap<usize, Vec<f32>>,
    /// The error of a failed batched call (every later call gets it too).
    failed: Option<String>,
}

#[derive(Debug, Default)]
struct Rounds {
    round: Mutex<Round>,
    changed: Condvar,
}

impl Rounds {
    fn lock(&self) -> MutexGuard<'_, Round> {
        // A panicking episode cannot leave the round half-written: every update below is
        // complete before the guard drops.
        self.round.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn wait<'a>(&self, g: MutexGuard<'a, Round>) -> MutexGuard<'a, Round> {
        self.changed.wait(g).unwrap_or_else(|e| e.into_inner())
    }

    /// Wait until every live episode has submitted a call (`Some`, the calls in episode
    /// order) or none is live (`None`).
    fn next_round(&self) -> Option<Vec<(usize, Call)>> {
        let mut r = self.lock();
        loop {
            if r.live == 0 {
                return None;
            }
            if r.calls.len() == r.live {
                return Some(std::mem::take(&mut r.calls).into_iter().collect());
            }
            r = self.wait(r);
        }
    }
}

/// The model an episode's head sees: each call goes to the shared round.
#[derive(Debug)]
struct Proxy {
    episode: usize,
    rounds: Arc<Rounds>,
}

impl VelocityModel for Proxy {
    fn backend(&self) -> &'static str {
        "batched"
    }

    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> Result<()> {
        input.validate()?;
        let want = input.batch * input.horizon * input.action_dim;
        if out.len() != want {
            return Err(Error::shape("out [B,H,A]", want, out.len()));
        }
        let mut r = self.rounds.lock();
        if let Some(e) = &r.failed {
            return Err(Error::Model(e.clone()));
        }
        r.calls.insert(self.episode, Call::new(input));
        self.rounds.changed.notify_all();
        loop {
            if let Some(v) = r.answers.remove(&self.episode) {
                out.copy_from_slice(&v);
                return Ok(());
            }
            if let Some(e) = &r.failed {
                return Err(Error::Model(e.clone()));
            }
            r = self.rounds.wait(r);
        }
    }
}

impl Drop for Proxy {
    fn drop(&mut self) {
        let mut r = self.rounds.lock();
        r.live -= 1;
        r.calls.remove(&self.episode);
        r.answers.remove(&self.episode);
        self.rounds.changed.notify_all();
    }
}

/// Run one round's calls as one batched call of `model`; the answers in the calls' order.
fn run_round<M: VelocityModel + ?Sized>(
    model: &mut M,
    calls: &[(usize, Call)],
) -> Result<Vec<Vec<f32>>> {
    let Some((_, first)) = calls.first() else {
        return Ok(Vec::new());
    };
    if let Some((ep, _)) = calls.iter().find(|(_, c)| !c.same_layout(first)) {
        return Err(Error::Config(format!(
            "batched evaluation: episode {ep} called the model with another input layout \
             than episode {}",
            calls[0].0
        )));
    }
    let cat = |f: fn(&Call) -> &[f32]| -> Vec<f32> {
        calls
            .iter()
            .flat_map(|(_, c)| f(c).iter().copied())
            .collect()
    };
    let batch: usize = calls.iter().map(|(_, c)| c.batch).sum();
    let (x, tau, obs_fast, slow_data) = (
        cat(|c| &c.x),
        cat(|c| &c.tau),
        cat(|c| &c.obs_fast),
        cat(|c| &c.slow),
    );
    let d_vis: Vec<u32> = calls
        .iter()
        .flat_map(|(_, c)| c.d_vis.iter().copied())
        .collect();
    let slow = match first.slow_layout {
        SlowLayout::None => SlowInput::None,
        SlowLayout::Vector { dim } => SlowInput::Vector {
            data: &slow_data,
            dim,
        },
        SlowLayout::Tokens { tokens, dim } => SlowInput::Tokens {
            data: &slow_data,
            tokens,
            dim,
        },
    };
    let input = ModelInput {
        batch,
        horizon: first.horizon,
        action_dim: first.action_dim,
        x: &x,
        tau: &tau,
        obs_fast: &obs_fast,
        n_obs: first.n_obs,
        fast_dim: first.fast_dim,
        slow,
        d_vis: &d_vis,
    };
    let row = first.horizon * first.action_dim;
    let mut out = vec![0.0f32; batch * row];
    model.velocity(&input, &mut out)?;
    let mut answers = Vec::with_capacity(calls.len());
    let mut at = 0;
    for (_, c) in calls {
        answers.push(out[at..at + c.batch * row].to_vec());
        at += c.batch * row;
    }
    Ok(answers)
}

/// [`crate::eval_cell`] with batched model calls: the episodes of `cell`, seeded as there,
/// run in consecutive groups of `group` episodes; the episodes of a group run side by side
/// on threads of their own, and their calls are answered by `model` in rounds, one batched
/// call per round (see the module docs). Returns the successes and the overrun ticks over
/// all episodes.
///
/// `make_env` is called once per episode. The result does not depend on thread timing; it
/// depends on `group` (the batches' composition) and on the model's batched arithmetic.
pub fn eval_cell_batched<E, M, FE>(
    make_env: &FE,
    model: &mut M,
    cell: &StudyCell<'_>,
    group: usize,
    progress: &(dyn Fn() + Sync),
) -> Result<(usize, u64)>
where
    E: Environment,
    M: VelocityModel + ?Sized,
    FE: Fn() -> E + Sync,
{
    let episodes = cell.episodes;
    let group = group.clamp(1, episodes.max(1));
    let mut total = (0usize, 0u64);
    let mut start = 0;
    while start < episodes {
        let end = (start + group).min(episodes);
        let rounds = Arc::new(Rounds::default());
        rounds.lock().live = end - start;
        let (results, round_error) = std::thread::scope(|s| {
            let handles: Vec<_> = (start..end)
                .map(|ep| {
                    let proxy = Proxy {
                        episode: ep,
                        rounds: Arc::clone(&rounds),
                    };
                    s.spawn(move || -> Result<(bool, u64)> {
                        let mut env = make_env();
                        // The proxy lives in the episode's head and is dropped with it,
                        // on success, error or panic alike.
                        let r = cell_episode(proxy, &mut env, cell, ep)?;
                        progress();
                        Ok((r.success, r.metrics.overruns))
                    })
                })
                .collect();
            let mut round_error = None;
            while let Some(calls) = rounds.next_round() {
                // A panic in the model must not leave the episodes waiting for an answer
                // (the scope would then wait for them forever): it fails the round.
                let ran = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    run_round(&mut *model, &calls)
                }))
                .unwrap_or_else(|p| Err(Error::panicked("batched model call", &*p)));
                match ran {
                    Ok(answers) => {
                        let mut r = rounds.lock();
                        for ((ep, _), a) in calls.iter().zip(answers) {
                            r.answers.insert(*ep, a);
                        }
                        rounds.changed.notify_all();
                    }
                    Err(e) => {
                        let mut r = rounds.lock();
                        r.failed = Some(e.to_string());
                        rounds.changed.notify_all();
                        drop(r);
                        round_error = Some(e);
                        break;
                    }
                }
            }
            let results: Vec<_> = handles
                .into_iter()
                .map(|h| {
                    h.join()
                        .unwrap_or_else(|p| Err(Error::panicked("evaluation episode", &*p)))
                })
                .collect();
            (results, round_error)
        });
        if let Some(e) = round_error {
            return Err(e);
        }
        for r in results {
            let (ok, overruns) = r?;
            total.0 += ok as usize;
            total.1 += overruns;
        }
        start = end;
    }
    Ok(total)
}
