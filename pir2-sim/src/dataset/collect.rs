//! Collection: an expert run on an environment into in-memory episodes.

use crate::error::{Error, Result};
use pir2_runtime::Environment;
use pir2_schedule::Rng;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

use super::*;

/// How demonstrations are collected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CollectConfig {
    /// Number of episodes to keep.
    pub episodes: usize,
    /// σ of the Gaussian noise added to the *executed* action (labels stay clean).
    pub action_noise: f64,
    /// Base seed; attempt `j` runs the environment with seed `episode_seed(seed, j)`.
    pub seed: u64,
    /// Keep only successful episodes (failed attempts are run and dropped).
    pub only_success: bool,
    /// Give up after this many attempts per kept episode (guards against an expert that
    /// never succeeds).
    pub max_attempts_per_episode: usize,
    /// Task index written with every episode.
    pub task_index: i64,
    /// [`collect_to_dataset`]: write the dataset to disk after every this many kept
    /// episodes (a killed collection loses at most this many minus one); 0 writes only at
    /// the end.
    pub flush_every: usize,
}

impl Default for CollectConfig {
    fn default() -> Self {
        Self {
            episodes: 200,
            action_noise: 0.01,
            seed: 0,
            only_success: true,
            max_attempts_per_episode: 20,
            task_index: 0,
            flush_every: 10,
        }
    }
}

/// The environment seed of attempt `attempt` under base seed `seed`.
pub fn episode_seed(seed: u64, attempt: u64) -> u64 {
    Rng::derive(seed, attempt).next_u64()
}

/// Progress of a collection, handed to the progress callback after every attempt.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Progress {
    /// Episodes kept so far (including ones already on disk when resuming).
    pub kept: usize,
    /// Episodes wanted in total.
    pub total: usize,
    /// Attempts run in this session.
    pub attempts: usize,
    /// Failed attempts in this session.
    pub failures: usize,
}

/// Summary of one collection session.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CollectStats {
    /// Episodes kept in this session.
    pub kept: usize,
    /// Attempts run in this session.
    pub attempts: usize,
    /// Failed attempts in this session.
    pub failures: usize,
    /// Index of the next attempt (to resume from).
    pub next_attempt: u64,
    /// The session ended early on its stop flag (after finishing the episode it was in).
    pub stopped: bool,
}

/// Run one demonstration episode: observe, ask the expert, execute the label plus noise.
pub fn run_episode<E, X>(
    env: &mut E,
    expert: &mut X,
    seed: u64,
    action_noise: f64,
    task_index: i64,
) -> Episode
where
    E: Environment,
    X: Expert<E> + ?Sized,
{
    let spec = env.spec();
    let mut ep = Episode::new(spec.fast_dim, spec.slow_dim, spec.action_dim);
    ep.seed = seed;
    ep.task_index = task_index;
    let (mut fast, mut slow) = (vec![0f32; spec.fast_dim], vec![0f32; spec.slow_dim]);
    let (mut label, mut exec) = (vec![0f32; spec.action_dim], vec![0f32; spec.action_dim]);
    let mut noise = Rng::derive(seed, 3);
    env.reset(seed);
    expert.reset(seed);
    for _ in 0..spec.max_steps {
        env.observe(&mut fast, &mut slow);
        expert.act(env, &mut label);
        for (e, l) in exec.iter_mut().zip(&label) {
            *e = (*l as f64 + action_noise * noise.normal() as f64) as f32;
        }
        ep.push(&fast, &slow, &label);
        let r = env.step(&exec);
        if r.done {
            ep.done = true;
            ep.success = r.success;
            break;
        }
    }
    ep
}

/// Collect demonstrations, handing each kept episode to `sink` and reporting progress.
/// `already` episodes count as kept (resume) and attempts start at `first_attempt`.
pub fn collect<E, X>(
    env: &mut E,
    expert: &mut X,
    cfg: &CollectConfig,
    already: usize,
    first_attempt: u64,
    progress: &mut dyn FnMut(&Progress),
    sink: &mut dyn FnMut(Episode, u64) -> Result<()>,
) -> Result<CollectStats>
where
    E: Environment,
    X: Expert<E> + ?Sized,
{
    let never = AtomicBool::new(false);
    collect_until(
        env,
        expert,
        cfg,
        already,
        first_attempt,
        &never,
        progress,
        sink,
    )
}

/// [`collect`] that ends early once `stop` is set (e.g. by Ctrl-C): the episode being run
/// is finished and handed to `sink` first, then the session returns with
/// [`CollectStats::stopped`] set.
pub fn collect_until<E, X>(
    env: &mut E,
    expert: &mut X,
    cfg: &CollectConfig,
    already: usize,
    first_attempt: u64,
    stop: &AtomicBool,
    progress: &mut dyn FnMut(&Progress),
    sink: &mut dyn FnMut(Episode, u64) -> Result<()>,
) -> Result<CollectStats>
where
    E: Environment,
    X: Expert<E> + ?Sized,
{
    let mut p = Progress {
        kept: already,
        total: cfg.episodes,
        attempts: 0,
        failures: 0,
    };
    let mut stats = CollectStats {
        next_attempt: first_attempt,
        ..Default::default()
    };
    let budget = cfg
        .episodes
        .saturating_sub(already)
        .saturating_mul(cfg.max_attempts_per_episode.max(1));
    progress(&p);
    while p.kept < cfg.episodes {
        if stop.load(Ordering::SeqCst) {
            stats.stopped = true;
            break;
        }
        if p.attempts >= budget {
            return Err(Error::ConfigValue {
                field: "max_attempts_per_episode",
                reason: format!(
                    "gave up after {} attempts with {} of {} episodes kept (the expert fails too often)",
                    p.attempts, p.kept, cfg.episodes
                ),
            });
        }
        let seed = episode_seed(cfg.seed, stats.next_attempt);
        let ep = run_episode(env, expert, seed, cfg.action_noise, cfg.task_index);
        let attempt = stats.next_attempt;
        stats.next_attempt += 1;
        p.attempts += 1;
        if !ep.success {
            p.failures += 1;
        }
        if ep.success || !cfg.only_success {
            sink(ep, attempt)?;
            p.kept += 1;
        }
        progress(&p);
    }
    stats.kept = p.kept - already;
    stats.attempts = p.attempts;
    stats.failures = p.failures;
    Ok(stats)
}

/// Collect demonstrations into memory.
pub fn collect_episodes<E, X>(
    env: &mut E,
    expert: &mut X,
    cfg: &CollectConfig,
    progress: &mut dyn FnMut(&Progress),
) -> Result<Vec<Episode>>
where
    E: Environment,
    X: Expert<E> + ?Sized,
{
    let mut out = Vec::with_capacity(cfg.episodes);
    collect(env, expert, cfg, 0, 0, progress, &mut |ep, _| {
        out.push(ep);
        Ok(())
    })?;
    Ok(out)
}

/// Collect demonstrations straight into a dataset at `root` (resuming if asked: only the
/// missing episodes are collected, continuing the attempt sequence), written to disk every
/// [`CollectConfig::flush_every`] kept episodes.
pub fn collect_to_dataset<E, X>(
    env: &mut E,
    expert: &mut X,
    cfg: &CollectConfig,
    root: &Path,
    spec: &DatasetSpec,
    mode: WriteMode,
    progress: &mut dyn FnMut(&Progress),
) -> Result<(CollectStats, DatasetSummary)>
where
    E: Environment,
    X: Expert<E> + ?Sized,
{
    let never = AtomicBool::new(false);
    collect_to_dataset_until(env, expert, cfg, root, spec, mode, &never, progress)
}

/// [`collect_to_dataset`] that ends early once `stop` is set: the episode being run is
/// finished, and the episodes kept so far are written (a [`WriteMode::Resume`] session
/// adds the rest later).
pub fn collect_to_dataset_until<E, X>(
    env: &mut E,
    expert: &mut X,
    cfg: &CollectConfig,
    root: &Path,
    spec: &DatasetSpec,
    mode: WriteMode,
    stop: &AtomicBool,
    progress: &mut dyn FnMut(&Progress),
) -> Result<(CollectStats, DatasetSummary)>
where
    E: Environment,
    X: Expert<E> + ?Sized,
{
    let mut writer = DatasetWriter::open(root, spec.clone(), mode)?;
    let already = writer.num_episodes();
    let first_attempt = writer.next_attempt();
    let stats = collect_until(
        env,
        expert,
        cfg,
        already,
        first_attempt,
        stop,
        progress,
        &mut |ep, attempt| {
            writer.append_attempt(&ep, attempt)?;
            if cfg.flush_every > 0 && writer.pending() >= cfg.flush_every {
                writer.flush()?;
            }
            Ok(())
        },
    )?;
    let summary = writer.finish()?;
    Ok((stats, summary))
}
