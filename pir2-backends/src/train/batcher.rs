//! Training batches built into reusable host buffers (the sampling of the module docs).

use super::*;

/// Encodes one sample's raw action chunk in place: `(episode, frame, chunk)`.
pub(crate) type ChunkEncoder<'a> = dyn FnMut(usize, usize, &mut [f32]) -> Result<()> + 'a;

/// Builds training batches into reusable host buffers.
pub(crate) struct Batcher {
    pub(crate) spec: Spec,
    pub(crate) stats: Stats,
    pub(crate) schedule: TrainSchedule,
    pub(crate) b: usize,
    pub(crate) rng: Rng,
    /// Cumulative frame counts per episode.
    pub(crate) cum: Vec<usize>,
    pub(crate) draw: Draw,
    pub(crate) act: Vec<f32>,
    pub(crate) eps: Vec<f32>,
    pub(crate) x: Vec<f32>,
    pub(crate) tau: Vec<f32>,
    pub(crate) target: Vec<f32>,
    pub(crate) mask: Vec<f32>,
    /// Normalised ground-truth chunks (for self-rollout).
    pub(crate) gt: Vec<f32>,
    pub(crate) epsb: Vec<f32>,
    pub(crate) fast: Vec<f32>,
    pub(crate) slow: Vec<f32>,
    pub(crate) dvis: Vec<u32>,
    /// Per sample, the `(episode, frame)` whose slow features it sees (`t − d_vis`, clamped
    /// at the episode start): for trainers that fetch slow features themselves.
    pub(crate) slow_frame: Vec<(usize, usize)>,
}

impl Batcher {
    pub(crate) fn new<D: Dataset + ?Sized>(
        data: &D,
        spec: &Spec,
        stats: &Stats,
        cfg: &TrainConfig,
    ) -> Self {
        let (h, a, b) = (spec.horizon, spec.action_dim, cfg.batch_size);
        let mut cum = Vec::with_capacity(data.num_episodes());
        let mut total = 0;
        for e in 0..data.num_episodes() {
            total += data.episode_len(e);
            cum.push(total);
        }
        Self {
            spec: *spec,
            stats: stats.clone(),
            schedule: cfg.schedule,
            b,
            rng: Rng::derive(cfg.seed, 0x0074_7261_696e),
            cum,
            draw: Draw::new(h),
            act: vec![0.0; h * a],
            eps: vec![0.0; h * a],
            x: vec![0.0; b * h * a],
            tau: vec![0.0; b * h],
            target: vec![0.0; b * h * a],
            mask: vec![0.0; b * h],
            gt: vec![0.0; b * h * a],
            epsb: vec![0.0; b * h * a],
            fast: vec![0.0; b * spec.n_obs * spec.fast_dim],
            slow: vec![0.0; b * spec.slow.len()],
            dvis: vec![0; b],
            slow_frame: vec![(0, 0); b],
        }
    }

    /// Draw only the frames whose whole chunk lies inside the episode (`t ≤ len − H`, none
    /// in an episode shorter than `H`), as GR00T's sampler does
    /// (`ShardedSingleStepDataset.get_effective_episode_length`), instead of every frame
    /// with the last action repeated past the end. The frames left are drawn uniformly;
    /// returns how many there are.
    pub(crate) fn full_chunks_only<D: Dataset + ?Sized>(&mut self, data: &D) -> usize {
        let h = self.spec.horizon;
        let mut total = 0;
        for (e, c) in self.cum.iter_mut().enumerate() {
            total += (data.episode_len(e) + 1).saturating_sub(h);
            *c = total;
        }
        total
    }

    pub(crate) fn fill<D: Dataset + ?Sized>(&mut self, data: &D) -> Result<()> {
        self.fill_encoded(data, None)
    }

    /// [`fill`](Self::fill), with the sample's action chunk turned into model coordinates by
    /// `encode(episode, frame, chunk)` (the chunk `[H, A]` of raw actions from `frame` on,
    /// the last action repeated past the episode's end) instead of the per-frame statistics:
    /// for targets that depend on the sample (relative actions). The draws are the same.
    pub(crate) fn fill_encoded<D: Dataset + ?Sized>(
        &mut self,
        data: &D,
        mut encode: Option<&mut ChunkEncoder<'_>>,
    ) -> Result<()> {
        let Spec {
            horizon: h,
            action_dim: a,
            n_obs,
            fast_dim: f,
            d_vis_max,
            ..
        } = self.spec;
        let sl = self.spec.slow.len();
        let total = *self.cum.last().unwrap_or(&0) as u64;
        for i in 0..self.b {
            let k = self.rng.below(total) as usize;
            let e = self.cum.partition_point(|&c| c <= k);
            let t = k - if e == 0 { 0 } else { self.cum[e - 1] };
            let len = data.episode_len(e);
            for j in 0..n_obs {
                let tt = (t + j + 1).saturating_sub(n_obs);
                self.fast[(i * n_obs + j) * f..(i * n_obs + j + 1) * f]
                    .copy_from_slice(data.fast(e, tt));
            }
            let dv = self.rng.below(d_vis_max as u64 + 1) as usize;
            self.dvis[i] = dv as u32;
            self.slow_frame[i] = (e, t.saturating_sub(dv));
            if sl > 0 {
                self.slow[i * sl..(i + 1) * sl].copy_from_slice(data.slow(e, t.saturating_sub(dv)));
            }
            for p in 0..h {
                self.act[p * a..(p + 1) * a].copy_from_slice(data.action(e, (t + p).min(len - 1)));
            }
            match encode.as_mut() {
                Some(f) => f(e, t, &mut self.act)?,
                None => self.stats.normalize_action(&mut self.act),
            }
            self.rng.fill_normal(&mut self.eps);
            self.schedule.draw(&mut self.rng, &mut self.draw)?;
            let r = i * h * a..(i + 1) * h * a;
            self.draw.build(
                &self.act,
                &self.eps,
                a,
                &mut self.x[r.clone()],
                &mut self.tau[i * h..(i + 1) * h],
                &mut self.target[r.clone()],
            )?;
            self.mask[i * h..(i + 1) * h].copy_from_slice(&self.draw.mask);
            self.gt[r.clone()].copy_from_slice(&self.act);
            self.epsb[r].copy_from_slice(&self.eps);
        }
        Ok(())
    }

    pub(crate) fn input(&self) -> ModelInput<'_> {
        let slow = match self.spec.slow {
            SlowSpec::None => SlowInput::None,
            SlowSpec::Vector { dim } => SlowInput::Vector {
                data: &self.slow,
                dim,
            },
            SlowSpec::Tokens { tokens, dim } => SlowInput::Tokens {
                data: &self.slow,
                tokens,
                dim,
            },
        };
        ModelInput {
            batch: self.b,
            horizon: self.spec.horizon,
            action_dim: self.spec.action_dim,
            x: &self.x,
            tau: &self.tau,
            obs_fast: &self.fast,
            n_obs: self.spec.n_obs,
            fast_dim: self.spec.fast_dim,
            slow,
            d_vis: &self.dvis,
        }
    }

    /// Replace a fraction of the samples by states the model reached itself (see [`SelfRollout`]).
    pub(crate) fn self_roll(&mut self, model: &mut CandleModel, r: SelfRollout) -> Result<()> {
        let (h, a) = (self.spec.horizon, self.spec.action_dim);
        let rows: Vec<bool> = (0..self.b).map(|_| self.rng.uniform() < r.prob).collect();
        if !rows.iter().any(|&s| s) {
            return Ok(());
        }
        // Start states: one step earlier on the noised ground truth (front and τ > 0.95 unchanged).
        let (x_final, tau_final) = (self.x.clone(), self.tau.clone());
        let mut tau_start = self.tau.clone();
        for (i, &row) in rows.iter().enumerate() {
            for p in 0..h {
                let q = i * h + p;
                let t = self.tau[q];
                if !row || self.mask[q] == 0.0 || !(0.0..=0.95).contains(&t) {
                    continue;
                }
                let ts = (t - r.step).max(0.0);
                tau_start[q] = ts;
                for j in q * a..(q + 1) * a {
                    self.x[j] = (1.0 - ts) * self.epsb[j] + ts * self.gt[j];
                }
            }
        }
        self.tau.copy_from_slice(&tau_start);
        let v = {
            let input = self.input();
            let mut v = vec![0.0f32; self.b * h * a];
            model.velocity_into(&input, &mut v)?;
            v
        };
        self.tau.copy_from_slice(&tau_final);
        for i in 0..self.b {
            for p in 0..h {
                let q = i * h + p;
                let (t, ts) = (tau_final[q], tau_start[q]);
                let r = q * a..(q + 1) * a;
                if ts == t {
                    self.x[r.clone()].copy_from_slice(&x_final[r]);
                    continue;
                }
                for ((x, tg), (&g, &vj)) in self.x[r.clone()]
                    .iter_mut()
                    .zip(&mut self.target[r.clone()])
                    .zip(self.gt[r.clone()].iter().zip(&v[r]))
                {
                    *x += (t - ts) * vj;
                    *tg = (g - *x) / (1.0 - t);
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// GR00T's sampling: only frames `t ≤ len − H` (the last chunk ending on the last frame
    /// included), every one of them, none from an episode shorter than `H`; without it,
    /// every frame.
    #[test]
    fn full_chunks_only_draws_the_frames_whose_chunk_fits() {
        let spec = Spec {
            horizon: 5,
            action_dim: 1,
            n_obs: 1,
            fast_dim: 1,
            slow: SlowSpec::None,
            d_vis_max: 0,
        };
        let data: Vec<Episode> = [7usize, 4, 5]
            .iter()
            .map(|&len| {
                let mut e = Episode::new(1, 0, 1);
                for t in 0..len {
                    e.push(&[t as f32], &[], &[t as f32]);
                }
                e
            })
            .collect();
        let cfg = TrainConfig {
            batch_size: 64,
            schedule: TrainSchedule::StandardFlow,
            ..TrainConfig::default()
        };
        let draws = |full: bool| {
            let mut b = Batcher::new(&data[..], &spec, &Stats::identity(&spec), &cfg);
            if full {
                assert_eq!(b.full_chunks_only(&data[..]), 3 + 1);
            }
            let mut seen = std::collections::BTreeSet::new();
            for _ in 0..8 {
                let mut record = |e: usize, t: usize, _: &mut [f32]| -> Result<()> {
                    seen.insert((e, t));
                    Ok(())
                };
                b.fill_encoded(&data[..], Some(&mut record)).unwrap();
            }
            seen.into_iter().collect::<Vec<_>>()
        };
        assert_eq!(draws(true), [(0, 0), (0, 1), (0, 2), (2, 0)]);
        assert_eq!(draws(false).len(), 7 + 4 + 5);
    }
}
