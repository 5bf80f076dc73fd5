//! What the trainer learns from: the [`Dataset`] trait, in-memory [`Episode`]s and the
//! normalisation statistics ([`compute_stats`]).

use super::*;

/// Frame-indexed demonstrations. Frames of one episode are consecutive control ticks.
pub trait Dataset {
    /// Number of episodes.
    fn num_episodes(&self) -> usize;
    /// Frames in episode `e` (≥ 1).
    fn episode_len(&self, e: usize) -> usize;
    /// Fast observation of frame `t` (`F` values).
    fn fast(&self, e: usize, t: usize) -> &[f32];
    /// Slow features of frame `t` (`S` or `T·D` values; empty without a slow channel).
    fn slow(&self, e: usize, t: usize) -> &[f32];
    /// Action of frame `t` (`A` values, raw units).
    fn action(&self, e: usize, t: usize) -> &[f32];
}

/// One in-memory episode: row-major per-frame fast obs, slow features and actions.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Episode {
    /// Fast observation width `F`.
    pub fast_dim: usize,
    /// Slow values per frame (`S` or `T·D`, 0 for none).
    pub slow_len: usize,
    /// Action width `A`.
    pub action_dim: usize,
    /// `[len, F]`.
    pub fast: Vec<f32>,
    /// `[len, slow_len]`.
    pub slow: Vec<f32>,
    /// `[len, A]`.
    pub action: Vec<f32>,
}

impl Episode {
    /// An empty episode with the given widths.
    pub fn new(fast_dim: usize, slow_len: usize, action_dim: usize) -> Self {
        Self {
            fast_dim,
            slow_len,
            action_dim,
            ..Default::default()
        }
    }
    /// Append one frame.
    pub fn push(&mut self, fast: &[f32], slow: &[f32], action: &[f32]) {
        debug_assert_eq!(fast.len(), self.fast_dim);
        debug_assert_eq!(slow.len(), self.slow_len);
        debug_assert_eq!(action.len(), self.action_dim);
        self.fast.extend_from_slice(fast);
        self.slow.extend_from_slice(slow);
        self.action.extend_from_slice(action);
    }
    /// Frames.
    pub fn len(&self) -> usize {
        self.action.len().checked_div(self.action_dim).unwrap_or(0)
    }
    /// Whether the episode has no frames.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl Dataset for [Episode] {
    fn num_episodes(&self) -> usize {
        self.len()
    }
    fn episode_len(&self, e: usize) -> usize {
        self[e].len()
    }
    fn fast(&self, e: usize, t: usize) -> &[f32] {
        let f = self[e].fast_dim;
        &self[e].fast[t * f..(t + 1) * f]
    }
    fn slow(&self, e: usize, t: usize) -> &[f32] {
        let s = self[e].slow_len;
        &self[e].slow[t * s..(t + 1) * s]
    }
    fn action(&self, e: usize, t: usize) -> &[f32] {
        let a = self[e].action_dim;
        &self[e].action[t * a..(t + 1) * a]
    }
}

pub(crate) fn check_dataset<D: Dataset + ?Sized>(data: &D, spec: &Spec) -> Result<()> {
    if data.num_episodes() == 0 {
        return Err(Error::Dataset("no episodes".into()));
    }
    for e in 0..data.num_episodes() {
        if data.episode_len(e) == 0 {
            return Err(Error::Dataset(format!("episode {e} is empty")));
        }
        let (f, s, a) = (
            data.fast(e, 0).len(),
            data.slow(e, 0).len(),
            data.action(e, 0).len(),
        );
        if f != spec.fast_dim || s != spec.slow.len() || a != spec.action_dim {
            return Err(Error::Dataset(format!(
                "episode {e}: frame widths fast/slow/action = {f}/{s}/{a}, the spec wants {}/{}/{}",
                spec.fast_dim,
                spec.slow.len(),
                spec.action_dim
            )));
        }
    }
    Ok(())
}

/// Normalisation statistics of a dataset (std floored at 1e-4): fast obs, successive fast
/// differences within episodes, slow features (per token width), actions.
pub fn compute_stats<D: Dataset + ?Sized>(data: &D, spec: &Spec) -> Result<Stats> {
    spec.validate()?;
    check_dataset(data, spec)?;
    let f = spec.fast_dim;
    let (mut fast, mut diff) = (Norm::accumulator(f), Norm::accumulator(f));
    let mut slow = Norm::accumulator(spec.slow.width());
    let mut act = Norm::accumulator(spec.action_dim);
    let mut d = vec![0.0f32; f];
    for e in 0..data.num_episodes() {
        for t in 0..data.episode_len(e) {
            let o = data.fast(e, t);
            fast.push(o);
            if t > 0 {
                for ((dj, &a), &b) in d.iter_mut().zip(o).zip(data.fast(e, t - 1)) {
                    *dj = a - b;
                }
                diff.push(&d);
            }
            if spec.slow.width() > 0 {
                for row in data.slow(e, t).chunks(spec.slow.width()) {
                    slow.push(row);
                }
            }
            act.push(data.action(e, t));
        }
    }
    let floor = 1e-4;
    Ok(Stats {
        fast: fast.finish(floor),
        fast_diff: diff.finish(floor),
        slow: slow.finish(floor),
        action: act.finish(floor),
    })
}
