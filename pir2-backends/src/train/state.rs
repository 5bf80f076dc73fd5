//! The training state carried from step to step, and its on-disk form: step checkpoints,
//! the `interrupted-*` state of a stopped run, and finding the latest to resume from.

use super::*;

/// Everything a run carries from one step to the next.
pub(crate) struct State {
    /// Steps done.
    pub(crate) step: usize,
    /// Raw (trained) weights, in [`CandleModel::vars`] order.
    pub(crate) params: Vec<Vec<f32>>,
    pub(crate) opt: AdamW,
    pub(crate) ema: Option<Vec<Vec<f32>>>,
    pub(crate) best: Option<(f64, Vec<Vec<f32>>)>,
    pub(crate) report: TrainReport,
}

/// The JSON part of a step checkpoint's training state.
#[derive(Debug, Serialize, Deserialize)]
pub(crate) struct StateMeta {
    pub(crate) step: usize,
    pub(crate) adam_t: u64,
    pub(crate) rng: [u64; 4],
    pub(crate) best_score: Option<f64>,
    pub(crate) config: TrainConfig,
    pub(crate) report: TrainReport,
}

impl State {
    /// Write the step checkpoint `dir` (the model's files, written by `write_model` into the
    /// directory it is given, + training state): into a
    /// uniquely named temp directory, every file fsynced, then renamed into place.
    pub(crate) fn save_step(
        &self,
        write_model: impl FnOnce(&Path) -> Result<()>,
        dir: &Path,
        rng: [u64; 4],
        names: &[String],
        cfg: &TrainConfig,
    ) -> Result<()> {
        crate::checkpoint::create_dir_durably(dir, |tmp| {
            write_model(tmp)?;
            let meta = StateMeta {
                step: self.step,
                adam_t: self.opt.t,
                rng,
                best_score: self.best.as_ref().map(|b| b.0),
                config: cfg.clone(),
                report: self.report.clone(),
            };
            let path = tmp.join(TRAIN_STATE_FILE);
            let text = serde_json::to_string(&meta).map_err(|e| Error::Format {
                path: path.clone(),
                message: e.to_string(),
            })?;
            crate::checkpoint::write_durable(&path, text.as_bytes())?;
            let mut tensors: Vec<(String, &[f32])> = Vec::new();
            for (i, n) in names.iter().enumerate() {
                tensors.push((format!("param/{n}"), &self.params[i]));
                tensors.push((format!("adam_m/{n}"), &self.opt.m[i]));
                tensors.push((format!("adam_v/{n}"), &self.opt.v[i]));
                if let Some(e) = &self.ema {
                    tensors.push((format!("ema/{n}"), &e[i]));
                }
                if let Some((_, b)) = &self.best {
                    tensors.push((format!("best/{n}"), &b[i]));
                }
            }
            crate::checkpoint::write_tensors(
                &tmp.join(TRAIN_TENSORS_FILE),
                tensors.into_iter().map(|(n, d)| (n, vec![d.len()], d)),
            )
        })
    }

    /// Read the training state of the step checkpoint `dir`; returns the batch generator.
    pub(crate) fn load(&mut self, dir: &Path, cfg: &TrainConfig, names: &[String]) -> Result<Rng> {
        let path = dir.join(TRAIN_STATE_FILE);
        let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
        let meta: StateMeta = serde_json::from_str(&text).map_err(|e| Error::Format {
            path: path.clone(),
            message: e.to_string(),
        })?;
        if meta.config != *cfg {
            return Err(Error::config(
                "train.resume",
                format!(
                    "{} was written with another training configuration ({:?}); resume needs the same",
                    path.display(),
                    meta.config
                ),
            ));
        }
        let tpath = dir.join(TRAIN_TENSORS_FILE);
        let bytes = std::fs::read(&tpath).map_err(|e| Error::io(&tpath, e))?;
        let st = safetensors::SafeTensors::deserialize(&bytes).map_err(|e| Error::Safetensors {
            path: tpath.clone(),
            message: e.to_string(),
        })?;
        let read = |key: String, want: usize| -> Result<Vec<f32>> {
            let v = st.tensor(&key).map_err(|e| Error::Safetensors {
                path: tpath.clone(),
                message: format!("`{key}`: {e}"),
            })?;
            let d: Vec<f32> = v
                .data()
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            if d.len() != want || v.dtype() != safetensors::Dtype::F32 {
                return Err(Error::shape("train state tensor", want, d.len()));
            }
            Ok(d)
        };
        for (i, n) in names.iter().enumerate() {
            let len = self.params[i].len();
            self.params[i] = read(format!("param/{n}"), len)?;
            self.opt.m[i] = read(format!("adam_m/{n}"), len)?;
            self.opt.v[i] = read(format!("adam_v/{n}"), len)?;
            if let Some(e) = self.ema.as_mut() {
                e[i] = read(format!("ema/{n}"), len)?;
            }
        }
        self.best = match meta.best_score {
            Some(s) => Some((
                s,
                names
                    .iter()
                    .zip(&self.params)
                    .map(|(n, p)| read(format!("best/{n}"), p.len()))
                    .collect::<Result<Vec<_>>>()?,
            )),
            None => None,
        };
        self.step = meta.step;
        self.opt.t = meta.adam_t;
        self.report = meta.report;
        Rng::from_state(meta.rng).ok_or_else(|| Error::Format {
            path,
            message: "all-zero random state".into(),
        })
    }
}

/// The step checkpoint with the highest step that carries a training state, if any.
/// Name prefix of the training state a stopped run leaves ([`Trainer::stop_on`]).
pub(crate) const INTERRUPTED_PREFIX: &str = "interrupted-";

/// Remove the `interrupted-*` training states of a finished run in `out`.
pub(crate) fn remove_interrupted(out: &Path) -> Result<()> {
    let Ok(rd) = std::fs::read_dir(out) else {
        return Ok(());
    };
    for e in rd.flatten() {
        if e.file_name()
            .to_string_lossy()
            .starts_with(INTERRUPTED_PREFIX)
        {
            std::fs::remove_dir_all(e.path()).map_err(|err| Error::io(e.path(), err))?;
        }
    }
    Ok(())
}

pub(crate) fn latest_step_checkpoint(out: &Path) -> Result<Option<PathBuf>> {
    let rd = match std::fs::read_dir(out) {
        Ok(rd) => rd,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(Error::io(out, e)),
    };
    let mut best: Option<(usize, PathBuf)> = None;
    let mut without_state = None;
    for e in rd.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(n) = name
            .strip_prefix("step-")
            .or_else(|| name.strip_prefix(INTERRUPTED_PREFIX))
            .and_then(|s| s.parse::<usize>().ok())
        else {
            continue;
        };
        if !e.path().join(TRAIN_STATE_FILE).is_file() {
            without_state = Some(e.path());
            continue;
        }
        if best.as_ref().is_none_or(|(b, _)| n > *b) {
            best = Some((n, e.path()));
        }
    }
    match (best, without_state) {
        (Some((_, p)), _) => Ok(Some(p)),
        (None, Some(p)) => Err(Error::config(
            "train.resume",
            format!("{} has no training state to resume from", p.display()),
        )),
        (None, None) => Ok(None),
    }
}
