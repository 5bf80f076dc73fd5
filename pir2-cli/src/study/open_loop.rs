//! Validation without an environment: the open-loop action error of the chunk a policy's
//! deployment sampler produces from recorded observations.
//!
//! For a window starting at frame `t` of a held-out episode, the runtime's [`ActionHead`] (in
//! the policy's deployment mode) gets the snapshot a robot would send at `t`: the fast
//! history `o_{t−n_obs+1..t}` (the first frame repeated before the episode start) and the
//! slow features of frame `t` (age 0). It samples one chunk as the deployed head does when it
//! starts, from noise:
//! - πR²: the staircase warm start at the validation delay `d` (every slot clean);
//! - flow (sync or naive async): one call, `K` Euler steps from noise;
//! - train-time RTC: the warm start, then one call at delay `d`, whose committed front is the
//!   warm start's first `d` actions and whose back is integrated in `K` steps.
//!
//! The chunk's actions (denormalised by the output map) are compared with the recorded
//! actions `a_{t..t+H}` over the slots inside the episode: RMSE in action units, and RMSE in
//! normalised units (each dimension divided by the dataset's action std, the output map's
//! scale), so that no dimension dominates by its units.

use anyhow::{bail, Result};
use serde::{Deserialize, Serialize};

use pir2_runtime::{
    ActionHead, Chunk, HeadSpec, LatencyWindow, Mode, ModelInput, OutputMap, Snapshot,
    VelocityModel,
};
use pir2_schedule::Rng;
use pir2_sim::dataset::Episode;

/// A borrowed model as a [`VelocityModel`] (the head owns its model; validation lends one).
struct Lent<'a, M>(&'a mut M);

impl<M: VelocityModel> VelocityModel for Lent<'_, M> {
    fn backend(&self) -> &'static str {
        self.0.backend()
    }
    fn velocity(&mut self, input: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
        self.0.velocity(input, out)
    }
}

/// How chunks are sampled for the open-loop error.
#[derive(Debug, Clone, PartialEq)]
pub struct OpenLoop {
    /// The head's sizes (period, `d_max`, `d_vis_max` as deployed).
    pub spec: HeadSpec,
    /// The deployment mode whose sampler is used.
    pub mode: Mode,
    /// Delay `d` of the πR² warm start and of the RTC call (clamped to the head's range).
    pub delay: usize,
    /// Model action space → action units.
    pub output: OutputMap,
    /// At most this many windows (evenly spread over all frames of the episodes).
    pub windows: usize,
    /// Seed of the sampling noise (window `i` uses a stream derived from it).
    pub seed: u64,
}

/// The open-loop action error of one model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OpenLoopError {
    /// Windows sampled.
    pub windows: usize,
    /// RMSE over every compared action entry, in action units.
    pub rmse: f64,
    /// RMSE with each action dimension divided by the dataset's action std.
    pub nrmse: f64,
}

/// The snapshot a robot would send at frame `t` of `e` (ticks of `period` ns, slow age 0).
pub fn snapshot(e: &Episode, t: usize, spec: &HeadSpec) -> Snapshot {
    let mut s = Snapshot::new(spec);
    let f = spec.fast_dim;
    for j in 0..spec.n_obs {
        let tt = (t + j + 1).saturating_sub(spec.n_obs);
        s.fast[j * f..(j + 1) * f].copy_from_slice(e.fast(tt));
    }
    s.slow.copy_from_slice(e.slow(t));
    s.tick = t as u64;
    s.t_state = t as u64 * spec.period;
    s.t_slow = s.t_state;
    s
}

/// Sample one chunk from `snap` with `mode`'s deployment sampler (see the module docs);
/// the chunk is in model action space, slot 0 at `snap.tick`.
pub fn sample_chunk<M: VelocityModel>(
    model: &mut M,
    spec: HeadSpec,
    mode: &Mode,
    delay: usize,
    snap: &Snapshot,
    seed: u64,
) -> Result<Chunk> {
    let window = LatencyWindow::new(20, 0, spec.period, spec.d_max);
    let mut head = ActionHead::new(Lent(model), spec, mode.head_mode(10), window, seed)?;
    let mut chunk = Chunk::new(spec.horizon, spec.action_dim);
    match mode {
        Mode::PiR2Sync { .. } | Mode::PiR2Async { .. } => {
            head.warm_start(snap, delay, &mut chunk)?;
        }
        Mode::SyncFlow { .. } | Mode::NaiveAsync { .. } => {
            head.force_delay(Some(delay));
            head.call(snap, &mut chunk)?;
        }
        Mode::TrainTimeRtc { .. } | Mode::InferenceRtc { .. } => {
            head.warm_start(snap, delay, &mut chunk)?;
            head.force_delay(Some(delay));
            head.call(snap, &mut chunk)?;
        }
    }
    Ok(chunk)
}

/// The open-loop action error of `model` on `episodes` (see the module docs).
pub fn open_loop_error<M: VelocityModel>(
    model: &mut M,
    episodes: &[Episode],
    cfg: &OpenLoop,
) -> Result<OpenLoopError> {
    let (h, a) = (cfg.spec.horizon, cfg.spec.action_dim);
    if cfg.output.scale.len() != a || cfg.output.offset.len() != a {
        bail!(
            "the output map has {} scales for {a} action dimensions",
            cfg.output.scale.len()
        );
    }
    let frames: Vec<(usize, usize)> = episodes
        .iter()
        .enumerate()
        .flat_map(|(e, ep)| (0..ep.len()).map(move |t| (e, t)))
        .collect();
    if frames.is_empty() {
        bail!("no held-out frames to validate on");
    }
    let n = cfg.windows.clamp(1, frames.len());
    let (mut se, mut sn, mut count) = (0.0f64, 0.0f64, 0usize);
    for i in 0..n {
        let (e, t) = frames[i * frames.len() / n];
        let ep = &episodes[e];
        let snap = snapshot(ep, t, &cfg.spec);
        let seed = Rng::derive(cfg.seed, i as u64).next_u64();
        let chunk = sample_chunk(model, cfg.spec, &cfg.mode, cfg.delay, &snap, seed)?;
        for p in 0..h.min(ep.len() - t) {
            let rec = ep.action(t + p);
            for j in 0..a {
                let x = chunk.x[p * a + j];
                let u = x * cfg.output.scale[j] + cfg.output.offset[j];
                let err = (u - rec[j]) as f64;
                se += err * err;
                let s = cfg.output.scale[j] as f64;
                sn += (err / s) * (err / s);
                count += 1;
            }
        }
    }
    let c = count.max(1) as f64;
    Ok(OpenLoopError {
        windows: n,
        rmse: (se / c).sqrt(),
        nrmse: (sn / c).sqrt(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A model whose velocity carries noise straight to a fixed normalised chunk `c`:
    /// `v = (c − x)/(1 − τ)`, so every sampler ends exactly at `c`.
    struct Target(Vec<f32>);

    impl VelocityModel for Target {
        fn backend(&self) -> &'static str {
            "target"
        }
        fn velocity(&mut self, i: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
            let a = i.action_dim;
            for (k, o) in out.iter_mut().enumerate() {
                let tau = i.tau[k / a].min(0.999);
                *o = (self.0[k % self.0.len()] - i.x[k]) / (1.0 - tau);
            }
            Ok(())
        }
    }

    fn spec() -> HeadSpec {
        HeadSpec {
            horizon: 8,
            action_dim: 2,
            n_obs: 2,
            fast_dim: 1,
            slow_dim: 0,
            period: 100_000_000,
            d_max: 2,
            d_vis_max: 0,
        }
    }

    fn episode(actions: &[[f32; 2]]) -> Episode {
        let mut e = Episode::new(1, 0, 2);
        for (t, a) in actions.iter().enumerate() {
            e.push(&[t as f32], &[], a);
        }
        e
    }

    #[test]
    fn the_error_is_zero_for_the_recorded_chunk_and_scales_with_the_offset() {
        let r = pir2_runtime::Recipe::default();
        // Recorded actions are constant (1, −2); the model's chunk is normalised (0.5, 0.5)
        // with scale (2, 4) and offset (0, −4): (1, −2) exactly.
        let ep = episode(&[[1.0, -2.0]; 10]);
        for policy in [
            pir2_runtime::Policy::Flow,
            pir2_runtime::Policy::Rtc,
            pir2_runtime::Policy::PiR2,
        ] {
            let mode = policy.deployments(&r)[0].mode;
            let cfg = OpenLoop {
                spec: spec(),
                mode,
                delay: 2,
                output: OutputMap {
                    scale: vec![2.0, 4.0],
                    offset: vec![0.0, -4.0],
                    clip: Vec::new(),
                    reference: Vec::new(),
                    poses: Vec::new(),
                },
                windows: 6,
                seed: 1,
            };
            let err = open_loop_error(&mut Target(vec![0.5, 0.5]), std::slice::from_ref(&ep), &cfg)
                .unwrap();
            assert_eq!(err.windows, 6);
            assert!(err.rmse < 1e-3 && err.nrmse < 1e-3, "{policy:?}: {err:?}");
            // Off by 0.25 normalised units in both dimensions: 0.5 and 1.0 in action units.
            let err = open_loop_error(
                &mut Target(vec![0.75, 0.75]),
                std::slice::from_ref(&ep),
                &cfg,
            )
            .unwrap();
            assert!((err.nrmse - 0.25).abs() < 1e-3, "{policy:?}: {err:?}");
            let want = ((0.5f64 * 0.5 + 1.0) / 2.0).sqrt();
            assert!((err.rmse - want).abs() < 1e-3, "{policy:?}: {err:?}");
        }
    }
}
