//! The one closed loop every stage runs a policy in (checkpoint validation in training, the
//! evaluation of a study, a ball-plate checkpoint's evaluation, remote or local): what runs
//! the action head ([`Models`]), how a cell's episodes run ([`EvalPath`]), [`closed_loop`]
//! itself, and the trained policies it is given ([`Trained`]).

use std::path::PathBuf;

use anyhow::Result;

use pir2_backends::candle::CandleModel;
use pir2_runtime::batched::eval_cell_batched;
use pir2_runtime::lockstep::{eval_cell, StudyCell};
use pir2_runtime::{HeadSpec, LockstepTiming, Mode, OutputMap, VelocityModel};

use super::{Policy, Scores, Settings, Task};

type MakeModel<'a> = Box<dyn Fn() -> Box<dyn VelocityModel> + Sync + 'a>;

/// What runs the action head in a closed loop: a factory of velocity models (one per
/// evaluation thread) and the map that denormalises their actions.
pub struct Models<'a> {
    output: OutputMap,
    make: MakeModel<'a>,
}

impl std::fmt::Debug for Models<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Models")
            .field("output", &self.output)
            .finish_non_exhaustive()
    }
}

impl<'a> Models<'a> {
    /// Models made by `make`, their actions denormalised by `output`.
    pub fn new(output: OutputMap, make: impl Fn() -> Box<dyn VelocityModel> + Sync + 'a) -> Self {
        Models {
            output,
            make: Box::new(make),
        }
    }

    /// Copies of a candle model (same weights, own scratch per thread).
    pub fn local(m: &CandleModel) -> Result<Models<'static>> {
        let weights = m.snapshot()?;
        let (config, stats) = (m.config().clone(), m.stats().clone());
        Ok(Models::new(output_map(m), move || {
            let mut c =
                CandleModel::new(config.clone(), stats.clone(), 0).expect("config was valid");
            c.restore(&weights).expect("same architecture");
            Box::new(c)
        }))
    }
}

/// The output map that denormalises a candle model's actions.
pub fn output_map(m: &CandleModel) -> OutputMap {
    let n = &m.stats().action;
    OutputMap {
        scale: n.std.clone(),
        offset: n.mean.clone(),
        clip: Vec::new(),
        reference: Vec::new(),
        poses: Vec::new(),
    }
}

/// The action head's spec for `policy` on `task`.
pub fn head_spec<T: Task>(task: &T, policy: Policy) -> HeadSpec {
    let s = task.spec();
    HeadSpec {
        horizon: s.horizon,
        action_dim: s.action_dim,
        n_obs: s.n_obs,
        fast_dim: s.fast_dim,
        slow_dim: s.slow.len(),
        period: task.period_ns(),
        d_max: policy.d_max(&task.settings().recipe),
        d_vis_max: s.d_vis_max,
    }
}

/// How the episodes of a closed-loop cell run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EvalPath {
    /// Every episode on its own with batch-1 model calls, this many episodes at a time
    /// ([`eval_cell`]).
    Threads(usize),
    /// Groups of this many episodes side by side, their calls answered by one batched call
    /// per round ([`eval_cell_batched`]).
    Batched(usize),
}

impl EvalPath {
    /// The path a study's settings ask for: batched when `batch_episodes > 1`.
    pub fn of(s: &Settings) -> Self {
        if s.batch_episodes > 1 {
            EvalPath::Batched(s.batch_episodes)
        } else {
            EvalPath::Threads(s.threads)
        }
    }

    /// What a cell measured this way is keyed by besides its checkpoint, row and column:
    /// `None` for batch-1 cells (whose bits do not depend on the thread count), the group
    /// size and the kernel thread count for batched ones (whose bits do).
    pub fn cell_tag(&self) -> Option<String> {
        match self {
            EvalPath::Threads(_) => None,
            EvalPath::Batched(g) => Some(format!(
                "batched g{g} k{}",
                pir2_backends::candle::kernel_threads()
            )),
        }
    }
}

/// Closed-loop successes (and overrun ticks) of `policy`'s models under `mode` with `timing`
/// over `episodes` episodes seeded from `seed`, run as `path` says.
#[allow(clippy::too_many_arguments)]
pub fn closed_loop<T: Task>(
    task: &T,
    models: &Models<'_>,
    policy: Policy,
    mode: &Mode,
    timing: LockstepTiming,
    episodes: usize,
    seed: u64,
    path: EvalPath,
    progress: &(dyn Fn() + Sync),
) -> Result<(usize, u64)> {
    let make_env = || {
        task.make_env()
            .expect("the task's environment config is valid")
    };
    let cell = StudyCell {
        head: head_spec(task, policy),
        mode: *mode,
        timing,
        output: &models.output,
        episodes,
        seed,
    };
    Ok(match path {
        EvalPath::Threads(threads) => {
            eval_cell(&make_env, &|| (models.make)(), &cell, threads, progress)?
        }
        EvalPath::Batched(group) => {
            eval_cell_batched(&make_env, (models.make)().as_mut(), &cell, group, progress)?
        }
    })
}

/// One trained `(policy, seed)`.
#[derive(Debug)]
pub struct Trained {
    /// Policy.
    pub policy: Policy,
    /// Seed.
    pub seed: u64,
    /// The chosen checkpoint.
    pub model: CandleModel,
    /// Its closed-loop validation scores (empty when loaded).
    pub scores: Scores,
    /// The training run's directory (`<root>/<policy>-seed<s>/`: `step-*` checkpoints and
    /// `best/`).
    pub dir: PathBuf,
}

/// Directory name of a trained policy under a checkpoints directory.
pub fn policy_dir(p: Policy, seed: u64) -> String {
    format!("{p:?}-seed{seed}").to_lowercase()
}
