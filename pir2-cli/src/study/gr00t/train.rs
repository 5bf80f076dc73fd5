//! `pir2 gr00t train`: πR² fine-tuning of a GR00T N1.7 checkpoint's action head on a
//! LeRobotDataset v3.0 with candle (feature `gr00t`), on the CPU by default or on the GPU
//! `--device` names (`cuda[:N]` with the `cuda` feature, `metal[:N]` with `metal`).
//!
//! Inputs:
//! - `--checkpoint N17_DIR`: GR00T N1.7's `config.json` and its `model.safetensors` (or
//!   sharded index); only the `action_head.*` tensors are read;
//! - `--data DATASET`: the demonstrations; the state is one float vector feature
//!   (`observation.state` by default) holding the embodiment's state groups in order, the
//!   action one (`action`) holding its action groups;
//! - `--embodiment embodiment.toml`: groups, norms, `H`, `d_max`, `d_vis_max`, `n_obs`, the
//!   embodiment slot, the state token's timestep and `[policy]` (what the head is trained as:
//!   the draws follow it, `pi_r2` with `nfe` by default);
//! - `--features FILE.safetensors`: the frozen backbone's outputs per frame
//!   ([`PrecomputedFeatures`]: `embeddings [N, T, D_vl]`, `image_mask [N, T]`, optional
//!   `attention_mask`), `N` = the dataset's frames in episode order.
//!
//! Samples are the frames whose whole action chunk lies inside their episode
//! (`t ≤ len − H`), as in GR00T's data pipeline. Relative action groups (`relative = true`)
//! train on GR00T's relative targets: slot `p` of the sample at frame `t` is `a_{t+p} − s_t`
//! (the raw state of frame `t`, the newest row of the observation window), normalised with
//! the slot's `relative_action` statistics ([`Gr00tTargets`]), computed over the same chunks
//! as GR00T's statistics tool.
//!
//! Output directory: `statistics.json` (GR00T's layout, computed from the dataset, per
//! group: min, max, mean, std, q01, q99; `relative_action` tables `[H, D]` for relative
//! groups), `embodiment.toml`, `gr00t_run.json` (the inputs'
//! digests), `vl-cache/` (the processed VL tokens, keyed by dataset + features + frozen head),
//! `loss.jsonl`, and `step-NNNNNN/` checkpoints (`model.safetensors` with GR00T's tensor names
//! and the delay table, `config.json`, the training state). The paper's robot recipe is the
//! default: AdamW, lr 1e-4 with 5 % warm-up and cosine decay, weight decay 1e-5, clip 1.0,
//! `d ~ U{1..d_max}`, `d_vis ~ U{0..d_vis_max}`, α = 0.2. GR00T's DiT dropout (the
//! checkpoint's `diffusion_model_cfg.dropout`, 0.2 in N1.7) applies in the training forward
//! unless `dropout` is off (`--no-dropout`); inference and export never drop.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pir2_backends::gr00t::n17::train::{
    head_fingerprint, tree_fingerprint, vl_cache_key, ActionTargets, Gr00tTrainSpec, Gr00tTrainer,
    PrecomputedFeatures, VlCache,
};
use pir2_backends::gr00t::n17::Gr00tN17Head;
use pir2_backends::gr00t::{EmbodimentConfig, Normalizer};
use pir2_backends::train::{Episode, Progress, TrainConfig, TrainReport};
use pir2_runtime::{DelayLaw, Recipe};
use pir2_schedule::train::TrainSchedule;
use pir2_sim::dataset::{check_selection, read_selected, FeatureSelection, FeatureStats};

use super::Gr00tTrainOptions;

/// What a run did.
#[derive(Debug, Clone)]
pub struct Gr00tTrainSummary {
    /// Losses and checkpoints.
    pub report: TrainReport,
    /// The VL-token cache used, and whether this run built it.
    pub cache: (PathBuf, bool),
}

fn group_list(groups: &[pir2_backends::gr00t::Group]) -> String {
    groups
        .iter()
        .map(|g| format!("{} {}", g.name, g.dim))
        .collect::<Vec<_>>()
        .join(" + ")
}

/// GR00T's `statistics.json` for `emb` from the dataset's raw states and actions: per
/// group `min`, `max`, `mean`, `std`, `q01`, `q99` (LeRobot's statistics, sliced by group).
fn statistics_json(
    emb: &EmbodimentConfig,
    episodes: &[pir2_sim::dataset::Episode],
) -> serde_json::Value {
    let gather = |f: &dyn Fn(&pir2_sim::dataset::Episode) -> &[f32]| -> Vec<f64> {
        episodes
            .iter()
            .flat_map(|e| f(e).iter().map(|&v| f64::from(v)))
            .collect()
    };
    let state = FeatureStats::compute(&gather(&|e| &e.fast), emb.state_dim());
    let action = FeatureStats::compute(&gather(&|e| &e.action), emb.action_dim());
    let groups = |s: &FeatureStats, groups: &[pir2_backends::gr00t::Group]| {
        let mut m = serde_json::Map::new();
        let mut at = 0;
        for g in groups {
            let r = at..at + g.dim;
            let q01 = quantile(s, "q01");
            let q99 = quantile(s, "q99");
            m.insert(
                g.name.clone(),
                serde_json::json!({
                    "min": s.min[r.clone()],
                    "max": s.max[r.clone()],
                    "mean": s.mean[r.clone()],
                    "std": s.std[r.clone()],
                    "q01": q01[r.clone()],
                    "q99": q99[r],
                }),
            );
            at += g.dim;
        }
        serde_json::Value::Object(m)
    };
    let mut tables = serde_json::Map::new();
    tables.insert("state".into(), groups(&state, &emb.state));
    tables.insert("action".into(), groups(&action, &emb.action));
    if emb.has_relative_actions() {
        tables.insert("relative_action".into(), relative_statistics(emb, episodes));
    }
    serde_json::json!({ emb.embodiment_tag.clone(): tables })
}

/// GR00T's `relative_action` statistics of every relative action group: per chunk slot `p`
/// (`[H, D]` tables), the statistics of `a_{t+p} − s_t` (a pose: `T_ref⁻¹·T` in the group's
/// layout; `s_t` the state group's raw value at `t`) over the chunks that lie inside their
/// episode, `t ∈ 0..=len − H` (the last one ends on the episode's last frame; an episode
/// shorter than `H` adds nothing), as GR00T's `RelativeActionLoader` takes them
/// (`usable_length = len − delta_indices[-1]`). These are exactly the chunks the trainer
/// draws, so no training target of a min/max group is clipped.
fn relative_statistics(
    emb: &EmbodimentConfig,
    episodes: &[pir2_sim::dataset::Episode],
) -> serde_json::Value {
    let h = emb.horizon;
    let reference = emb.action_reference();
    let poses = emb.action_poses();
    let mut out = serde_json::Map::new();
    let mut at = 0;
    for g in &emb.action {
        let cols = at..at + g.dim;
        at += g.dim;
        if !g.relative {
            continue;
        }
        let pose = poses.iter().find(|p| p.first == cols.start);
        let k0 = reference[cols.start].unwrap_or(0);
        let mut rows: Vec<FeatureStats> = Vec::with_capacity(h);
        let (mut values, mut rel) = (Vec::new(), vec![0f32; g.dim]);
        for p in 0..h {
            values.clear();
            for e in episodes {
                for t in 0..(e.len() + 1).saturating_sub(h) {
                    let (a, s) = (e.action(t + p), e.fast(t));
                    match pose {
                        Some(pg) => {
                            pir2_runtime::pose::relative(
                                pg.format,
                                &s[k0..k0 + g.dim],
                                &a[cols.clone()],
                                &mut rel,
                            );
                            values.extend(rel.iter().map(|&v| f64::from(v)));
                        }
                        None => {
                            for j in cols.clone() {
                                let k = reference[j].unwrap_or(0);
                                values.push(f64::from(a[j]) - f64::from(s[k]));
                            }
                        }
                    }
                }
            }
            rows.push(FeatureStats::compute(&values, g.dim));
        }
        let table = |f: &dyn Fn(&FeatureStats) -> Vec<f64>| -> Vec<Vec<f64>> {
            rows.iter().map(f).collect()
        };
        out.insert(
            g.name.clone(),
            serde_json::json!({
                "min": table(&|s| s.min.clone()),
                "max": table(&|s| s.max.clone()),
                "mean": table(&|s| s.mean.clone()),
                "std": table(&|s| s.std.clone()),
                "q01": table(&|s| quantile(s, "q01")),
                "q99": table(&|s| quantile(s, "q99")),
            }),
        );
    }
    serde_json::Value::Object(out)
}

/// The training targets of `pir2 gr00t train`: every slot `p` of a sample's chunk encoded
/// with GR00T's processor ([`Normalizer::encode_action`] at slot `p`) against the raw state
/// of the sample's frame `t`, the newest row of its observation window. A relative group's
/// target is `a_{t+p} − s_t` normalised with the slot's `relative_action` statistics; an
/// absolute group's is its normalised action. The runtime decodes slot `p` of the chunk a
/// call makes from the snapshot at tick `t` against the raw state of that snapshot's newest
/// row (`OutputMap::decode`, the reference filled by `OutputMap::fill_reference`), and
/// executes it at tick `t + p`: the same pairing of state and action.
#[derive(Debug, Clone)]
pub struct Gr00tTargets {
    norm: Normalizer,
    horizon: usize,
    action_dim: usize,
    /// Raw states per episode, `[len, S]`.
    states: Vec<Vec<f32>>,
    state_dim: usize,
}

impl Gr00tTargets {
    /// The targets of `episodes` (raw dataset states and actions) under `norm` for chunks of
    /// `horizon` slots.
    pub fn new(norm: Normalizer, horizon: usize, episodes: &[pir2_sim::dataset::Episode]) -> Self {
        Self {
            action_dim: norm.action_dim(),
            state_dim: norm.state_dim(),
            norm,
            horizon,
            states: episodes.iter().map(|e| e.fast.clone()).collect(),
        }
    }
}

impl ActionTargets for Gr00tTargets {
    fn encode(&self, episode: usize, frame: usize, chunk: &mut [f32]) -> pir2_backends::Result<()> {
        let (sd, a) = (self.state_dim, self.action_dim);
        let s = self
            .states
            .get(episode)
            .and_then(|s| s.get(frame * sd..(frame + 1) * sd))
            .ok_or_else(|| {
                pir2_backends::Error::Dataset(format!(
                    "no frame {frame} in episode {episode} of the training targets"
                ))
            })?;
        if chunk.len() != self.horizon * a {
            return Err(pir2_backends::Error::Dataset(format!(
                "an action chunk of {} values, expected H × A = {} × {a}",
                chunk.len(),
                self.horizon
            )));
        }
        for (p, x) in chunk.chunks_exact_mut(a).enumerate() {
            self.norm.encode_action(p, s, x);
        }
        Ok(())
    }
}

/// Write `text` to `path`, or, when the file exists (a resumed run), check it is the same.
fn write_or_check(path: &Path, text: &str, resume: bool) -> Result<()> {
    if resume && path.exists() {
        let old =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        if old != text {
            bail!(
                "{} differs from what this run computes from its inputs; resume needs the same \
                 dataset and embodiment",
                path.display()
            );
        }
        return Ok(());
    }
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// The checks that the N1.7 head of configuration `c` (from `checkpoint`) can serve the
/// embodiment `emb` (from `embodiment`): history, widths, slot, timestep buckets, horizon.
pub(super) fn check_head_fits(
    emb: &EmbodimentConfig,
    c: &pir2_backends::gr00t::n17::Gr00tN17Config,
    checkpoint: &Path,
    embodiment: &Path,
) -> Result<()> {
    let ck = checkpoint.display();
    let ed = embodiment.display();
    if emb.n_obs != c.state_history_length {
        bail!(
            "embodiment {ed}: n_obs = {} but the checkpoint {ck} has state_history_length = {}",
            emb.n_obs,
            c.state_history_length
        );
    }
    if emb.encoded_state_dim() > c.max_state_dim {
        bail!(
            "embodiment {ed}: the state is {} values wide as the model sees it, the checkpoint {ck} \
             takes max_state_dim = {}",
            emb.encoded_state_dim(),
            c.max_state_dim
        );
    }
    if emb.action_dim() > c.max_action_dim {
        bail!(
            "embodiment {ed}: {} action values, the checkpoint {ck} has max_action_dim = {}",
            emb.action_dim(),
            c.max_action_dim
        );
    }
    if emb.embodiment_id < 0 || emb.embodiment_id as usize >= c.max_num_embodiments {
        bail!(
            "embodiment {ed}: embodiment_id {} is not a slot of the checkpoint {ck} (0..{})",
            emb.embodiment_id,
            c.max_num_embodiments
        );
    }
    if emb.num_timestep_buckets as usize != c.num_timestep_buckets {
        bail!(
            "embodiment {ed}: num_timestep_buckets = {}, the checkpoint {ck} has {}",
            emb.num_timestep_buckets,
            c.num_timestep_buckets
        );
    }
    if c.add_pos_embed && emb.horizon > c.max_seq_len {
        bail!(
            "embodiment {ed}: horizon {} is longer than the checkpoint's position embedding ({ck}: max_seq_len = {})",
            emb.horizon,
            c.max_seq_len
        );
    }

    Ok(())
}

/// The embodiment `embodiment` and the head of `checkpoint` as `pir2 gr00t train` trains it,
/// on the candle device `device` (`cpu`, `cuda[:N]`, `metal[:N]`; a GPU the build lacks is
/// one error naming its feature): trainable, with the delay table of `d_vis_max + 1` rows and,
/// for a policy trained with them, per-position AdaLN heads; checked against the embodiment.
pub(super) fn load_head(
    checkpoint: &Path,
    embodiment: &Path,
    device: &str,
) -> Result<(EmbodimentConfig, Gr00tN17Head)> {
    let device = pir2_backends::candle::device(device)?;
    let emb = EmbodimentConfig::load(embodiment)
        .with_context(|| format!("embodiment {}", embodiment.display()))?;
    let mut head = Gr00tN17Head::load_trainable(checkpoint, emb.d_vis_max, &device)
        .with_context(|| format!("GR00T N1.7 checkpoint {}", checkpoint.display()))?;
    // The paper's architecture: πR² gives every DiT token its own AdaLN head, initialised from
    // the checkpoint's shared pair (the baselines keep GR00T's shared modulation).
    if emb.policy.trained.per_position_heads() {
        head = head
            .with_position_heads(emb.horizon)
            .with_context(|| format!("GR00T N1.7 checkpoint {}", checkpoint.display()))?;
    }
    check_head_fits(&emb, head.config(), checkpoint, embodiment)?;
    Ok((emb, head))
}

/// The paper's robot recipe for `emb` (AdamW, lr with 5 % warm-up and cosine decay, weight
/// decay 1e-5, clip 1.0, the draws of the policy `emb` trains).
pub(super) fn train_config(
    emb: &EmbodimentConfig,
    steps: usize,
    batch_size: usize,
    lr: f64,
    seed: u64,
    checkpoint_every: Option<usize>,
) -> TrainConfig {
    let recipe = Recipe {
        nfe: emb.policy.nfe,
        flow_steps: emb.policy.flow_steps,
        delays: DelayLaw::Uniform,
        pir2_d_max: emb.d_max,
        rtc_d_max: 10,
        jitter: 0.0,
        ..Recipe::default()
    };
    TrainConfig {
        steps,
        batch_size,
        lr,
        min_lr: 0.0,
        warmup: steps / 20,
        betas: (0.95, 0.999),
        eps: 1e-8,
        weight_decay: 1e-5,
        grad_clip: Some(1.0),
        ema: None,
        seed,
        schedule: gr00t_schedule(emb.policy.trained.schedule(&recipe)),
        checkpoint_every,
        self_rollout: None,
        log_every: 10,
    }
}

/// The trainer's view of `emb`.
pub(super) fn train_spec(emb: &EmbodimentConfig) -> Gr00tTrainSpec {
    Gr00tTrainSpec {
        horizon: emb.horizon,
        action_dim: emb.action_dim(),
        d_vis_max: emb.d_vis_max,
        embodiment_id: emb.embodiment_id as u32,
        state_timestep: emb.state_timestep() as u32,
    }
}

/// `pir2 gr00t train` (see the module docs).
pub fn train(
    o: &Gr00tTrainOptions,
    mut progress: impl FnMut(&Progress),
) -> Result<Gr00tTrainSummary> {
    let (emb, head) = load_head(&o.checkpoint, &o.embodiment, &o.device)?;
    let c = head.config().clone();
    let ck = o.checkpoint.display();
    let ed = o.embodiment.display();

    // The dataset: widths first, against the embodiment.
    let sel = FeatureSelection {
        fast: vec![o.state_key.clone()],
        slow: Vec::new(),
        action: o.action_key.clone(),
    };
    let dd = o.data.display();
    let feats = check_selection(&o.data, &sel).with_context(|| format!("dataset {dd}"))?;
    for (key, want, groups) in [
        (&o.state_key, emb.state_dim(), group_list(&emb.state)),
        (&o.action_key, emb.action_dim(), group_list(&emb.action)),
    ] {
        if let Some(f) = feats.iter().find(|f| &f.key == key) {
            if f.width != want {
                bail!(
                    "dataset {dd}: `{key}` has {} values per frame, the embodiment {ed} has {want} ({groups})",
                    f.width
                );
            }
        }
    }
    let ds = read_selected(&o.data, &sel).with_context(|| format!("dataset {dd}"))?;
    let frames: usize = ds.episodes.iter().map(|e| e.len()).sum();
    if frames == 0 {
        bail!("dataset {dd} has no frames");
    }
    let longest = ds.episodes.iter().map(|e| e.len()).max().unwrap_or(0);
    if longest < emb.horizon {
        bail!(
            "dataset {dd}: no episode holds one whole action chunk of the embodiment's horizon \
             H = {} frames (the longest has {longest}); GR00T trains only on chunks inside an \
             episode",
            emb.horizon
        );
    }

    // Statistics → GR00T's normalisation, written for export and deployment.
    std::fs::create_dir_all(&o.out).with_context(|| format!("creating {}", o.out.display()))?;
    let stats_path = o.out.join("statistics.json");
    let stats_text = serde_json::to_string_pretty(&statistics_json(&emb, &ds.episodes))?;
    write_or_check(&stats_path, &stats_text, o.resume)?;
    let emb_text = std::fs::read_to_string(&o.embodiment)?;
    write_or_check(&o.out.join("embodiment.toml"), &emb_text, o.resume)?;
    let norm = Normalizer::load(&stats_path, &emb)?;
    let (sw, a) = (c.max_state_dim, emb.action_dim());
    let enc = emb.encoded_state_dim();
    let episodes: Vec<Episode> = ds
        .episodes
        .iter()
        .map(|e| {
            let mut out = Episode::new(sw, 0, a);
            let mut s = vec![0f32; sw];
            for t in 0..e.len() {
                s.fill(0.0);
                norm.normalize_state(e.fast(t), &mut s[..enc]);
                // Raw: the targets are encoded per sample (`Gr00tTargets`).
                out.push(&s, &[], e.action(t));
            }
            out
        })
        .collect();
    let targets = Gr00tTargets::new(norm, emb.horizon, &ds.episodes);

    // The frozen backbone's tokens: cached once per frame, keyed by everything they depend on.
    let features = PrecomputedFeatures::open(&o.features)
        .with_context(|| format!("backbone features {}", o.features.display()))?;
    if features.frames() != frames {
        bail!(
            "backbone features {}: {} frames, the dataset {dd} has {frames}",
            o.features.display(),
            features.frames()
        );
    }
    if features.dim() != c.backbone_embedding_dim {
        bail!(
            "backbone features {}: tokens of width {}, the checkpoint {ck} has backbone_embedding_dim = {}",
            o.features.display(),
            features.dim(),
            c.backbone_embedding_dim
        );
    }
    let data_fp = tree_fingerprint(&o.data, &["meta", "data"])?;
    let feat_fp = features.fingerprint()?;
    let key = vl_cache_key(&head, &data_fp, &feat_fp)?;
    let (mut cache, built) =
        VlCache::open_or_build(&o.out.join("vl-cache"), &key, &head, &features)?;

    let cfg = train_config(
        &emb,
        o.steps,
        o.batch_size,
        o.lr,
        o.seed,
        o.checkpoint_every,
    );
    let spec = train_spec(&emb);
    let identity = serde_json::json!({
        "checkpoint": head_fingerprint(&head)?,
        "dataset": data_fp,
        "features": feat_fp,
        "vl_cache": key,
        "embodiment": emb_text,
        "state_key": o.state_key,
        "action_key": o.action_key,
    });
    let config_json = std::fs::read(o.checkpoint.join("config.json"))?;
    let mut trainer = Gr00tTrainer::new(cfg, spec, &o.out)
        .resume(o.resume)
        .identity(identity)
        .checkpoint_file("config.json", config_json)
        .action_targets(&targets)
        .dropout(o.dropout)
        .on_progress(&mut progress);
    if let Some(s) = &o.stop {
        trainer = trainer.stop_on(s.clone());
    }
    if let Some(n) = o.stop_after {
        trainer = trainer.stop_after(n);
    }
    let report = trainer.run(&head, &episodes, &mut cache)?;
    Ok(Gr00tTrainSummary {
        report,
        cache: (cache.path().to_path_buf(), built),
    })
}

/// The named quantile row (`q01`, `q99`, ...) of `s`.
///
/// # Panics
///
/// If `name` is not one of [`pir2_sim::dataset::QUANTILES`]: the callers pass the literal
/// names GR00T's statistics need, so that is a bug here, not bad input.
fn quantile(s: &FeatureStats, name: &str) -> Vec<f64> {
    let i = pir2_sim::dataset::QUANTILES
        .iter()
        .position(|(_, n)| *n == name)
        .unwrap_or_else(|| {
            panic!("`{name}` is not among pir2_sim::dataset::QUANTILES; GR00T's statistics use q01 and q99, which it computes")
        });
    s.quantiles[i].clone()
}

/// The draws of a GR00T head: the recipe's, with the flow baseline's shared `τ` drawn from
/// GR00T N1.7's own law (`pir2_schedule::train::gr00t_n17_tau`, `τ = 0.999·(1 − B)`,
/// `B ~ Beta(1.5, 1)`) instead of `U[0, 1]`, so a `trained = "flow"` head is trained as GR00T
/// trains its head. The πR² and train-time-RTC draws are πR²'s.
fn gr00t_schedule(s: TrainSchedule) -> TrainSchedule {
    match s {
        TrainSchedule::StandardFlow => TrainSchedule::Gr00tFlow,
        other => other,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_flow_baseline_draws_gr00ts_tau_law() {
        use pir2_runtime::Policy;
        let r = Recipe::default();
        assert_eq!(
            gr00t_schedule(Policy::Flow.schedule(&r)),
            TrainSchedule::Gr00tFlow
        );
        assert!(matches!(
            gr00t_schedule(Policy::PiR2.schedule(&r)),
            TrainSchedule::PiR2(_)
        ));
    }

    #[test]
    fn quantile_rows_are_found_by_name() {
        let data: Vec<f64> = (0..=100).map(f64::from).collect();
        let s = FeatureStats::compute(&data, 1);
        assert_eq!(quantile(&s, "q01"), [1.0]);
        assert_eq!(quantile(&s, "q99"), [99.0]);
    }

    #[test]
    #[should_panic(expected = "`q42` is not among")]
    fn an_unknown_quantile_is_a_bug() {
        quantile(&FeatureStats::compute(&[0.0], 1), "q42");
    }
}
