//! GR00T's per-group normalisation of the state and the action (maps in the parent module's
//! docs), read from the checkpoint's `statistics.json`.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Deserialize;

use super::{EmbodimentConfig, Group, Norm};
use crate::error::{Error, Result};

/// GR00T's per-group normalisation of the state and the action (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Normalizer {
    /// `norm(x) = (x − state_offset) · state_inv_scale`, per raw state dimension (a
    /// degenerate min/max dimension has `inv_scale = 0`: it maps to 0; a zero-std one has
    /// offset 0 and `inv_scale = 1`).
    state_offset: Vec<f32>,
    state_inv_scale: Vec<f32>,
    /// Clip the normalised state to `[-1, 1]` (min/max and percentile groups).
    state_clip: Vec<bool>,
    /// The state groups in order: `(first raw dimension, width, sin/cos encoded)`.
    state_groups: Vec<(usize, usize, bool)>,
    /// `raw = scale · clip(x) + offset (+ reference)`, per action dimension (`[A]`), or per
    /// chunk slot and action dimension (`[H, A]`) when a relative group has per-slot
    /// statistics.
    action_scale: Vec<f32>,
    action_offset: Vec<f32>,
    /// Clip the model's action to `[-1, 1]` before denormalising (min/max and percentile).
    action_clip: Vec<bool>,
    /// Per action dimension, the raw state index a relative action is added to.
    action_reference: Vec<Option<usize>>,
    /// The relative end-effector poses among the relative dimensions (composed with the
    /// reference pose, not added per dimension).
    action_poses: Vec<pir2_runtime::PoseGroup>,
    /// A degenerate min/max (or percentile) action dimension (numpy's `isclose(max, min)`),
    /// laid out like `action_scale` (`[A]` or `[H, A]`): normalises to 0.
    action_zero: Vec<bool>,
}

/// One statistic as `statistics.json` holds it: `[D]`, or `[H, D]` (per chunk slot, GR00T's
/// `relative_action` statistics).
#[derive(Debug, Clone, Deserialize)]
#[serde(untagged)]
enum Stat {
    Flat(Vec<f64>),
    Table(Vec<Vec<f64>>),
}

impl Stat {
    fn shape(&self) -> String {
        match self {
            Stat::Flat(v) => format!("[{}]", v.len()),
            Stat::Table(t) => {
                let w = t.first().map_or(0, Vec::len);
                if t.iter().all(|r| r.len() == w) {
                    format!("[{}, {w}]", t.len())
                } else {
                    format!("[{}, rows of unequal length]", t.len())
                }
            }
        }
    }
}

/// A group's affine map per row (one row, or one per chunk slot) and dimension:
/// `norm = (x − offset)/scale`, `raw = scale·norm + offset`; `zero` marks a degenerate
/// min/max dimension, which normalises to 0.
struct GroupAffine {
    rows: usize,
    offset: Vec<f32>,
    scale: Vec<f32>,
    clip: bool,
    zero: Vec<bool>,
}

/// Largest magnitude a statistic may have: joint angles, positions in metres and gripper
/// widths are all far below it, so a larger value is a broken file (a unit error or a
/// sentinel such as 1e30), not a robot's range, and is refused by name.
pub const MAX_STAT_ABS: f64 = 1e6;

type StatsFile = BTreeMap<String, BTreeMap<String, BTreeMap<String, BTreeMap<String, Stat>>>>;

impl Normalizer {
    /// The identity (no statistics).
    pub fn identity(state_dim: usize, action_dim: usize) -> Self {
        Normalizer {
            state_offset: vec![0.0; state_dim],
            state_inv_scale: vec![1.0; state_dim],
            state_clip: vec![false; state_dim],
            state_groups: vec![(0, state_dim, false)],
            action_scale: vec![1.0; action_dim],
            action_offset: vec![0.0; action_dim],
            action_clip: vec![false; action_dim],
            action_reference: vec![None; action_dim],
            action_poses: Vec::new(),
            action_zero: vec![false; action_dim],
        }
    }

    /// Load GR00T's `statistics.json` for `cfg` (every group and statistic its norm needs
    /// must be present with the group's width; the error names the missing key). A relative
    /// action group reads `relative_action.<group>`, of shape `[H, D]` (per chunk slot) or
    /// `[D]`; another shape is one error naming the key and both shapes.
    pub fn load(path: &Path, cfg: &EmbodimentConfig) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let stats: StatsFile = serde_json::from_str(&text).map_err(|e| Error::Parse {
            path: path.to_path_buf(),
            message: format!(
                "expected {{embodiment: {{modality: {{group: {{stat: [numbers] or \
                 [[numbers]]}}}}}}}}: {e}"
            ),
        })?;
        Self::from_stats(&stats, path, cfg)
    }

    fn from_stats(stats: &StatsFile, path: &Path, cfg: &EmbodimentConfig) -> Result<Self> {
        let err = |modality: &str, group: &str, stat: &str, problem: String| Error::Statistics {
            path: path.to_path_buf(),
            key: format!("{}.{modality}.{group}.{stat}", cfg.embodiment_tag),
            problem,
        };
        let emb = stats.get(&cfg.embodiment_tag).ok_or_else(|| {
            err(
                "*",
                "*",
                "*",
                format!(
                    "is missing: no embodiment `{}` (found {:?})",
                    cfg.embodiment_tag,
                    stats.keys().collect::<Vec<_>>()
                ),
            )
        })?;
        let horizon = cfg.horizon;
        // A statistic as rows × dim values; `[H, D]` only where `per_slot`.
        let get =
            |modality: &str, g: &Group, stat: &str, per_slot: bool| -> Result<(usize, Vec<f64>)> {
                let v = emb
                    .get(modality)
                    .and_then(|m| m.get(&g.name))
                    .and_then(|s| s.get(stat))
                    .ok_or_else(|| err(modality, &g.name, stat, "is missing".to_string()))?;
                let (rows, flat) = match v {
                    Stat::Flat(v) if v.len() == g.dim => (1, v.clone()),
                    Stat::Flat(v) if !per_slot => {
                        return Err(err(
                            modality,
                            &g.name,
                            stat,
                            format!("has {} values, the group has dim {}", v.len(), g.dim),
                        ))
                    }
                    Stat::Table(t)
                        if per_slot && t.len() == horizon && t.iter().all(|r| r.len() == g.dim) =>
                    {
                        (horizon, t.concat())
                    }
                    other => {
                        let want = if per_slot {
                            format!("[{horizon}, {d}] (per chunk slot) or [{d}]", d = g.dim)
                        } else {
                            format!("[{}]", g.dim)
                        };
                        return Err(err(
                            modality,
                            &g.name,
                            stat,
                            format!("has shape {}, expected {want}", other.shape()),
                        ));
                    }
                };
                if flat.iter().any(|x| !x.is_finite()) {
                    return Err(err(modality, &g.name, stat, "is not finite".to_string()));
                }
                if let Some((i, x)) = flat
                    .iter()
                    .enumerate()
                    .find(|(_, x)| x.abs() > MAX_STAT_ABS)
                {
                    return Err(err(
                        modality,
                        &g.name,
                        stat,
                        format!(
                            "[{}] = {x:e} is beyond ±{MAX_STAT_ABS:e}: not a robot's range \
                             (a unit error or a sentinel value?)",
                            i % g.dim
                        ),
                    ));
                }
                Ok((rows, flat))
            };
        let affine = |modality: &str, g: &Group| -> Result<GroupAffine> {
            let per_slot = modality == "relative_action";
            let mut out = GroupAffine {
                rows: 1,
                offset: Vec::new(),
                scale: Vec::new(),
                clip: false,
                zero: Vec::new(),
            };
            match g.norm {
                Norm::MinMax | Norm::Q01Q99 => {
                    let (lo_name, hi_name) = if g.norm == Norm::MinMax {
                        ("min", "max")
                    } else {
                        ("q01", "q99")
                    };
                    let ((rl, lo), (rh, hi)) = (
                        get(modality, g, lo_name, per_slot)?,
                        get(modality, g, hi_name, per_slot)?,
                    );
                    out.rows = rl.max(rh);
                    out.clip = true;
                    for i in 0..out.rows * g.dim {
                        let (l, h) = (lo[i % (rl * g.dim)], hi[i % (rh * g.dim)]);
                        if l > h {
                            // An inverted range would flip every action of the dimension.
                            let slot = if out.rows > 1 {
                                format!(" (chunk slot {})", i / g.dim)
                            } else {
                                String::new()
                            };
                            return Err(err(
                                modality,
                                &g.name,
                                hi_name,
                                format!(
                                    "[{}] = {h} is below {lo_name}[{}] = {l}{slot}: the range \
                                     is inverted",
                                    i % g.dim,
                                    i % g.dim
                                ),
                            ));
                        }
                        // numpy's isclose(max, min): such a dimension normalises to 0.
                        out.zero.push((h - l).abs() <= 1e-8 + 1e-5 * l.abs());
                        out.offset.push(((l + h) / 2.0) as f32);
                        out.scale.push(((h - l) / 2.0) as f32);
                    }
                }
                Norm::MeanStd => {
                    let ((rm, mean), (rs, std)) = (
                        get(modality, g, "mean", per_slot)?,
                        get(modality, g, "std", per_slot)?,
                    );
                    out.rows = rm.max(rs);
                    for i in 0..out.rows * g.dim {
                        let (m, sd) = (mean[i % (rm * g.dim)], std[i % (rs * g.dim)]);
                        if sd < 0.0 {
                            return Err(err(
                                modality,
                                &g.name,
                                "std",
                                format!("[{}] = {sd} is negative", i % g.dim),
                            ));
                        }
                        // GR00T passes a zero-std dimension through unchanged.
                        let (o, sc) = if sd == 0.0 { (0.0, 1.0) } else { (m, sd) };
                        out.offset.push(o as f32);
                        out.scale.push(sc as f32);
                        out.zero.push(false);
                    }
                }
                Norm::None | Norm::SinCos => {
                    out.offset = vec![0.0; g.dim];
                    out.scale = vec![1.0; g.dim];
                    out.zero = vec![false; g.dim];
                }
            }
            Ok(out)
        };
        let (mut so, mut ss, mut sc, mut sz) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let mut state_groups = Vec::with_capacity(cfg.state.len());
        for g in &cfg.state {
            let m = affine("state", g)?;
            state_groups.push((so.len(), g.dim, g.norm == Norm::SinCos));
            so.extend(m.offset);
            ss.extend(m.scale);
            sc.extend(std::iter::repeat_n(m.clip, g.dim));
            sz.extend(m.zero);
        }
        let actions = cfg
            .action
            .iter()
            .map(|g| {
                affine(
                    if g.relative {
                        "relative_action"
                    } else {
                        "action"
                    },
                    g,
                )
            })
            .collect::<Result<Vec<_>>>()?;
        // Per chunk slot as soon as one group has per-slot statistics.
        let rows = actions.iter().map(|m| m.rows).max().unwrap_or(1);
        let (mut ao, mut ascale, mut aclip, mut azero) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for p in 0..rows {
            for (g, m) in cfg.action.iter().zip(&actions) {
                let r = if m.rows == 1 { 0 } else { p };
                ao.extend_from_slice(&m.offset[r * g.dim..(r + 1) * g.dim]);
                ascale.extend_from_slice(&m.scale[r * g.dim..(r + 1) * g.dim]);
                azero.extend_from_slice(&m.zero[r * g.dim..(r + 1) * g.dim]);
                if p == 0 {
                    aclip.extend(std::iter::repeat_n(m.clip, g.dim));
                }
            }
        }
        Ok(Normalizer {
            state_offset: so,
            state_inv_scale: ss
                .iter()
                .zip(&sz)
                .map(|(&s, &zero)| if zero { 0.0 } else { 1.0 / s })
                .collect(),
            state_clip: sc,
            state_groups,
            action_scale: ascale,
            action_offset: ao,
            action_clip: aclip,
            action_reference: cfg.action_reference(),
            action_poses: cfg.action_poses(),
            action_zero: azero,
        })
    }

    /// Raw state width (what the robot reports).
    pub fn state_dim(&self) -> usize {
        self.state_offset.len()
    }

    /// State width as the model sees it (sin/cos groups count twice).
    pub fn encoded_state_dim(&self) -> usize {
        self.state_groups
            .iter()
            .map(|&(_, w, sc)| if sc { 2 * w } else { w })
            .sum()
    }

    /// Normalise one raw state vector (`state_dim` values) into `out`
    /// (`encoded_state_dim` values), group by group.
    pub fn normalize_state(&self, raw: &[f32], out: &mut [f32]) {
        debug_assert!(raw.len() >= self.state_dim() && out.len() >= self.encoded_state_dim());
        let mut o = 0;
        for &(first, width, sin_cos) in &self.state_groups {
            let x = &raw[first..first + width];
            if sin_cos {
                for (k, v) in x.iter().enumerate() {
                    out[o + k] = v.sin();
                    out[o + width + k] = v.cos();
                }
                o += 2 * width;
                continue;
            }
            for (k, v) in x.iter().enumerate() {
                let i = first + k;
                let n = (v - self.state_offset[i]) * self.state_inv_scale[i];
                out[o + k] = if self.state_clip[i] {
                    n.clamp(-1.0, 1.0)
                } else {
                    n
                };
            }
            o += width;
        }
    }

    /// Action width.
    pub fn action_dim(&self) -> usize {
        self.action_clip.len()
    }

    /// Whether the action statistics are per chunk slot (`[H, A]`).
    pub fn per_slot(&self) -> bool {
        self.action_scale.len() > self.action_dim()
    }

    /// Normalise one raw absolute action vector in place with the first slot's statistics, as
    /// GR00T's processor does for training targets: `(x − offset)/scale`, clipped to `[-1, 1]`
    /// for the min/max and percentile groups; a degenerate min/max dimension maps to 0.
    /// [`Self::denormalize_action`] inverts it inside the clip range. Relative groups are not
    /// referenced here (their targets depend on the chunk's start state).
    pub fn normalize_action(&self, a: &mut [f32]) {
        for (i, x) in a.iter_mut().enumerate() {
            if self.action_zero[i] {
                *x = 0.0;
                continue;
            }
            let n = (*x - self.action_offset[i]) / self.action_scale[i];
            *x = if self.action_clip[i] {
                n.clamp(-1.0, 1.0)
            } else {
                n
            };
        }
    }

    /// GR00T's training target for the action at `slot` of a chunk whose observation's newest
    /// raw state is `state` (the inverse of [`decode_action`](Self::decode_action) inside the
    /// clip range): subtract the reference state from the relative groups (`a − s`; a relative
    /// end-effector pose becomes `T_ref⁻¹·T`, see `pir2_runtime::pose`), then
    /// normalise with that slot's statistics, `(x − offset)/scale`, clipped to `[-1, 1]` for
    /// the min/max and percentile groups; a degenerate min/max dimension of that slot maps to
    /// 0. In place. `state` is only read for relative groups (pass `&[]` without any).
    pub fn encode_action(&self, slot: usize, state: &[f32], a: &mut [f32]) {
        let n = self.action_dim();
        let row = if self.per_slot() { slot * n } else { 0 };
        for g in &self.action_poses {
            let r = g.dims();
            let k = self.action_reference[g.first].unwrap_or(0);
            let mut abs = [0f32; 9];
            abs[..r.len()].copy_from_slice(&a[r.clone()]);
            pir2_runtime::pose::relative(
                g.format,
                &state[k..k + r.len()],
                &abs[..r.len()],
                &mut a[r],
            );
        }
        for (i, x) in a.iter_mut().enumerate() {
            if self.action_zero[row + i] {
                *x = 0.0;
                continue;
            }
            let mut u = *x;
            if let Some(k) = self.action_reference[i].filter(|_| !self.in_pose(i)) {
                u -= state[k];
            }
            let v = (u - self.action_offset[row + i]) / self.action_scale[row + i];
            *x = if self.action_clip[i] {
                v.clamp(-1.0, 1.0)
            } else {
                v
            };
        }
    }

    /// Denormalise one absolute action vector in place with the first slot's statistics
    /// (relative groups get no reference: see [`decode_action`](Self::decode_action)).
    pub fn denormalize_action(&self, a: &mut [f32]) {
        for (i, x) in a.iter_mut().enumerate() {
            let v = if self.action_clip[i] {
                x.clamp(-1.0, 1.0)
            } else {
                *x
            };
            *x = self.action_scale[i] * v + self.action_offset[i];
        }
    }

    /// GR00T's decoding of the action at `slot` of a chunk made from an observation whose
    /// newest raw state is `state`: denormalise with that slot's statistics (clipping the
    /// min/max and percentile groups first), then add the reference state to the relative
    /// groups (compose a relative end-effector pose with the reference pose, `T_ref·T_rel`).
    /// In place.
    pub fn decode_action(&self, slot: usize, state: &[f32], a: &mut [f32]) {
        let n = self.action_dim();
        let row = if self.per_slot() { slot * n } else { 0 };
        for (i, x) in a.iter_mut().enumerate() {
            let v = if self.action_clip[i] {
                x.clamp(-1.0, 1.0)
            } else {
                *x
            };
            let mut u = self.action_scale[row + i] * v + self.action_offset[row + i];
            if let Some(k) = self.action_reference[i].filter(|_| !self.in_pose(i)) {
                u += state[k];
            }
            *x = u;
        }
        for g in &self.action_poses {
            let r = g.dims();
            let k = self.action_reference[g.first].unwrap_or(0);
            let mut rel = [0f32; 9];
            rel[..r.len()].copy_from_slice(&a[r.clone()]);
            pir2_runtime::pose::absolute(
                g.format,
                &state[k..k + r.len()],
                &rel[..r.len()],
                &mut a[r],
            );
        }
    }

    /// Whether action dimension `i` belongs to a relative pose.
    fn in_pose(&self, i: usize) -> bool {
        self.action_poses.iter().any(|g| g.dims().contains(&i))
    }

    /// The runtime's output map that turns model actions into absolute joint targets
    /// (per-slot statistics and the relative groups' state indices included).
    pub fn action_output_map(&self) -> pir2_runtime::OutputMap {
        let reference = if self.action_reference.iter().any(Option::is_some) {
            self.action_reference.clone()
        } else {
            Vec::new()
        };
        pir2_runtime::OutputMap {
            scale: self.action_scale.clone(),
            offset: self.action_offset.clone(),
            clip: self.action_clip.clone(),
            reference,
            poses: self.action_poses.clone(),
        }
    }
}
