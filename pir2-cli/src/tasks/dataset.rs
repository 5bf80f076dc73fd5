//! `pir2 train --data DATASET --task task.toml --out DIR`: a policy on a user's own
//! state-only LeRobotDataset v3.0 ([`crate::study::dataset`]), picked on held-out episodes.

use std::path::Path;

use anyhow::{bail, Result};

use super::TrainOptions;
use crate::study::dataset::{self, DatasetTaskConfig};

/// Train the task file `file`'s policy; prints each checkpoint's held-out scores.
pub fn train(o: &TrainOptions, file: &Path) -> Result<()> {
    if o.policy.is_some() || o.config.is_some() || o.seed != 0 {
        bail!(
            "--policy, --config and --seed are for the stock tasks; with --task the task file \
             names the policy, the model and the seed"
        );
    }
    let cfg = DatasetTaskConfig::load(file)?;
    let r = dataset::train(&o.data, &cfg, &o.out, o.resume).map_err(|e| {
        super::with_resume_hint(
            e,
            &format!(
                "pir2 train --task {} --data {} --out {} --resume",
                file.display(),
                o.data.display(),
                o.out.display()
            ),
        )
    })?;
    println!("held-out episodes: {:?}", r.held_out);
    println!("step      flow loss  open-loop RMSE  (normalised)");
    for c in &r.checkpoints {
        println!(
            "{:<9} {:<10.4} {:<15.4} {:.4}{}",
            c.step,
            c.flow_loss,
            c.open_loop.rmse,
            c.open_loop.nrmse,
            if Some(c.step) == r.best_step {
                "  ← best"
            } else {
                ""
            }
        );
    }
    println!(
        "best checkpoint (lowest {}): {}",
        r.metric,
        o.out.join("best").display()
    );
    Ok(())
}
