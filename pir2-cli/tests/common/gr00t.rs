//! Shared set-up of the GR00T integration tests: the tiny `alt` head fixture of
//! `pir2-backends` as a checkpoint (and its form widened to more state and action values),
//! the small embodiments and synthetic backbone features the trainer takes, the `pir2` binary
//! runner, Python reference scripts, and the lock-step stand-ins (a replayed episode and a
//! head that outputs the training targets) that check a trained relative group deploys back
//! to the dataset.

use std::collections::HashMap;
use std::ffi::{OsStr, OsString};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use candle_core::{Device, Tensor};
use pir2_backends::gr00t::n17::train::ActionTargets;
use pir2_backends::gr00t::{EmbodimentConfig, Group, GroupFormat, Norm};
use pir2_cli::study::gr00t::Gr00tTargets;
use pir2_runtime::{EnvSpec, EnvStep, Environment, ModelInput, OutputMap, VelocityModel};
use pir2_sim::dataset::{Dataset, FeatureSelection};

/// Tokens per frame of the synthetic features of the `alt` head: 0-1 text, 2-4 image,
/// 5 padding.
pub const TOKENS: usize = 6;
/// `D_vl` of the `alt` head.
pub const ALT_D_VL: usize = 20;
/// The control period of the tests' embodiments (25 Hz), in ns.
const PERIOD_NS: u64 = 40_000_000;

/// The reference fixtures of the GR00T N1.7 head (`pir2-backends`).
pub fn alt_fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../pir2-backends/tests/fixtures/gr00t_n17_head")
}

/// The `alt` fixture as a checkpoint directory (GR00T's tensor names; max_state_dim 6, state
/// history 2, max_action_dim 5, 8 positions, D_vl 20, 3 embodiment slots).
pub fn alt_checkpoint(dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::copy(
        alt_fixtures().join("alt.config.json"),
        dir.join("config.json"),
    )
    .unwrap();
    std::fs::copy(
        alt_fixtures().join("alt.weights.safetensors"),
        dir.join("model.safetensors"),
    )
    .unwrap();
}

/// A deterministic stream of values in `[-0.1, 0.1)` (xorshift).
pub fn padding(seed: &mut u64, n: usize) -> Vec<f32> {
    (0..n)
        .map(|_| {
            *seed ^= *seed << 13;
            *seed ^= *seed >> 7;
            *seed ^= *seed << 17;
            ((*seed >> 11) as f64 / (1u64 << 53) as f64 * 0.2 - 0.1) as f32
        })
        .collect()
}

/// `t` (`[n, rows, cols]`) widened to `[n, rows_of(r), cols_of(c)]`: entry `(i, r, c)` of
/// the old tensor lands at `(i, rows_of(r), cols_of(c))`; every other entry is seeded padding.
fn widen(
    t: &Tensor,
    rows: usize,
    cols: usize,
    row_of: impl Fn(usize) -> usize,
    col_of: impl Fn(usize) -> usize,
    seed: &mut u64,
) -> Tensor {
    let (n, r0, c0) = t.dims3().unwrap();
    let old = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let mut v = padding(seed, n * rows * cols);
    for i in 0..n {
        for r in 0..r0 {
            for c in 0..c0 {
                v[(i * rows + row_of(r)) * cols + col_of(c)] = old[(i * r0 + r) * c0 + c];
            }
        }
    }
    Tensor::from_vec(v, (n, rows, cols), &Device::Cpu).unwrap()
}

/// The `alt` fixture (max_state_dim 6 × state history 2, max_action_dim 5) as a checkpoint
/// with `max_action_dim = max_state_dim = wide`: GR00T's tensors that depend on those widths
/// (`action_encoder.W1`, `action_decoder.layer2`, `state_encoder.layer1`, one `[W, b]` per
/// embodiment slot) keep the fixture's values at the old positions and get seeded padding in
/// the new rows and columns; everything else is the fixture's.
pub fn wide_alt_checkpoint(dir: &Path, wide: usize) {
    std::fs::create_dir_all(dir).unwrap();
    let mut cfg = read_json(&alt_fixtures().join("alt.config.json"));
    let (old_s, old_a) = (6, 5);
    assert_eq!(cfg["max_state_dim"], old_s);
    assert_eq!(cfg["max_action_dim"], old_a);
    let history = cfg["state_history_length"].as_u64().unwrap() as usize;
    cfg["max_state_dim"] = wide.into();
    cfg["max_action_dim"] = wide.into();
    std::fs::write(
        dir.join("config.json"),
        serde_json::to_string_pretty(&cfg).unwrap(),
    )
    .unwrap();

    let mut w: HashMap<String, Tensor> = candle_core::safetensors::load(
        alt_fixtures().join("alt.weights.safetensors"),
        &Device::Cpu,
    )
    .unwrap();
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    let id = |i: usize| i;
    let p = "action_head.";
    // Action encoder input: [n, A_max, D_in].
    let k = format!("{p}action_encoder.W1.W");
    let d_in = w[&k].dims3().unwrap().2;
    let t = widen(&w[&k], wide, d_in, id, id, &mut seed);
    w.insert(k, t);
    // Action decoder output: [n, hid, A_max] and [n, A_max].
    let k = format!("{p}action_decoder.layer2.W");
    let hid = w[&k].dims3().unwrap().1;
    let t = widen(&w[&k], hid, wide, id, id, &mut seed);
    w.insert(k, t);
    let k = format!("{p}action_decoder.layer2.b");
    let b = w[&k].unsqueeze(1).unwrap();
    let t = widen(&b, 1, wide, id, id, &mut seed).squeeze(1).unwrap();
    w.insert(k, t);
    // State encoder input: history × max_state_dim, step-major ([n, hist · S_max, hid]).
    let k = format!("{p}state_encoder.layer1.W");
    let hid = w[&k].dims3().unwrap().2;
    let t = widen(
        &w[&k],
        history * wide,
        hid,
        |r| (r / old_s) * wide + r % old_s,
        id,
        &mut seed,
    );
    w.insert(k, t);
    candle_core::safetensors::save(&w, dir.join("model.safetensors")).unwrap();
}

/// An absolute group of `dim` values in the default layout.
pub fn group(name: &str, dim: usize, norm: Norm) -> Group {
    Group {
        name: name.into(),
        dim,
        norm,
        relative: false,
        state_key: None,
        format: GroupFormat::Default,
    }
}

/// The xArm6 + XHand embodiment cut down for the `alt` head: `name`, horizon `horizon`,
/// d_max = 2, d_vis_max = 2, n_obs = 2, slot 1 (its groups are the caller's).
pub fn small_embodiment(name: &str, horizon: usize) -> EmbodimentConfig {
    let mut e = EmbodimentConfig::xarm6_xhand();
    e.name = name.into();
    e.horizon = horizon;
    e.d_max = 2;
    e.d_vis_max = 2;
    e.n_obs = 2;
    e.embodiment_id = 1;
    e
}

/// [`small_embodiment`] `tiny` with state `arm` (`state_arm` values, min/max) + `grip` (1,
/// mean/std) and action `arm` (3, min/max) + `grip` (1, percentiles).
pub fn arm_grip_embodiment(horizon: usize, state_arm: usize) -> EmbodimentConfig {
    let mut e = small_embodiment("tiny", horizon);
    e.state = vec![
        group("arm", state_arm, Norm::MinMax),
        group("grip", 1, Norm::MeanStd),
    ];
    e.action = vec![
        group("arm", 3, Norm::MinMax),
        group("grip", 1, Norm::Q01Q99),
    ];
    e
}

/// Backbone outputs for the `alt` head: the embeddings `emb` (`[N, TOKENS, 20]`) with the
/// image mask (tokens 2-4) and the attention mask (all but token 5) of every frame.
pub fn write_alt_features(path: &Path, emb: Tensor) {
    let dev = Device::Cpu;
    let frames = emb.dims3().unwrap().0;
    let image: Vec<u8> = (0..frames).flat_map(|_| [0u8, 0, 1, 1, 1, 0]).collect();
    let attn: Vec<u8> = (0..frames).flat_map(|_| [1u8, 1, 1, 1, 1, 0]).collect();
    let map = HashMap::from([
        ("embeddings".to_string(), emb),
        (
            "image_mask".to_string(),
            Tensor::from_vec(image, (frames, TOKENS), &dev).unwrap(),
        ),
        (
            "attention_mask".to_string(),
            Tensor::from_vec(attn, (frames, TOKENS), &dev).unwrap(),
        ),
    ]);
    candle_core::safetensors::save(&map, path).unwrap();
}

/// The dataset's state as the fast row and its action (what `pir2 gr00t train` reads).
pub fn state_and_action() -> FeatureSelection {
    FeatureSelection {
        fast: vec!["observation.state".into()],
        slow: Vec::new(),
        action: "action".into(),
    }
}

/// A JSON file.
pub fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// The `pir2` binary with `args`.
pub fn pir2<S: AsRef<OsStr>>(args: &[S]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pir2"))
        .args(args)
        .output()
        .expect("runs pir2")
}

/// What a run printed: stdout, then stderr.
pub fn text(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr)
}

/// [`pir2`] and its [`text`].
pub fn pir2_text<S: AsRef<OsStr>>(args: &[S]) -> (Output, String) {
    let out = pir2(args);
    let t = text(&out);
    (out, t)
}

/// `gr00t train --checkpoint ck --data data --embodiment emb --features feats --out out`.
pub fn train_args(ck: &Path, data: &Path, emb: &Path, feats: &Path, out: &Path) -> Vec<OsString> {
    let mut v: Vec<OsString> = ["gr00t", "train"].map(OsString::from).to_vec();
    for (flag, p) in [
        ("--checkpoint", ck),
        ("--data", data),
        ("--embodiment", emb),
        ("--features", feats),
        ("--out", out),
    ] {
        v.push(flag.into());
        v.push(p.into());
    }
    v
}

/// Writes `source` to `script` and runs it with `$PIR2_PYTHON` (`python`) on `args`; the run
/// must succeed (`what` names it in the failure).
pub fn run_python(python: &Path, script: &Path, source: &str, args: &[&OsStr], what: &str) {
    std::fs::write(script, source).unwrap();
    let out = Command::new(python).arg(script).args(args).output();
    let out = out.unwrap_or_else(|e| panic!("{what}: {}: {e}", python.display()));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{what}: {stderr}");
}

/// Replays one episode's raw states (the fast row is the raw state, as on the robot) and
/// records the commands it is sent.
struct Replay {
    width: usize,
    states: Vec<Vec<f32>>,
    t: usize,
    sent: Vec<Vec<f32>>,
}

impl Environment for Replay {
    fn spec(&self) -> EnvSpec {
        EnvSpec {
            fast_dim: self.width,
            slow_dim: 0,
            action_dim: self.width,
            control_period: PERIOD_NS,
            max_steps: self.states.len(),
        }
    }
    fn reset(&mut self, _seed: u64) {
        self.t = 0;
        self.sent.clear();
    }
    fn observe(&mut self, fast: &mut [f32], _slow: &mut [f32]) {
        fast.copy_from_slice(&self.states[self.t]);
    }
    fn step(&mut self, action: &[f32]) -> EnvStep {
        self.sent.push(action.to_vec());
        self.t += 1;
        EnvStep {
            done: self.t >= self.states.len(),
            success: true,
            reward: 0.0,
        }
    }
}

/// A head that outputs the training target exactly: it finds the dataset frame of the
/// snapshot's newest raw state and steers every slot to what the trainer's own encoder
/// ([`Gr00tTargets`]) makes of that frame's chunk.
struct TargetOracle {
    targets: Gr00tTargets,
    episode: usize,
    states: Vec<Vec<f32>>,
    actions: Vec<Vec<f32>>,
    chunk: Vec<f32>,
}

impl VelocityModel for TargetOracle {
    fn backend(&self) -> &'static str {
        "training-target oracle"
    }
    fn velocity(&mut self, inp: &ModelInput<'_>, out: &mut [f32]) -> pir2_runtime::Result<()> {
        let (h, a, f) = (inp.horizon, inp.action_dim, inp.fast_dim);
        let newest = &inp.obs_fast[(inp.n_obs - 1) * f..inp.n_obs * f];
        let t = self
            .states
            .iter()
            .position(|s| s.as_slice() == newest)
            .expect("the snapshot's state is a dataset frame");
        let len = self.actions.len();
        for p in 0..h {
            self.chunk[p * a..(p + 1) * a].copy_from_slice(&self.actions[(t + p).min(len - 1)]);
        }
        self.targets
            .encode(self.episode, t, &mut self.chunk)
            .map_err(|e| pir2_runtime::Error::Config(e.to_string()))?;
        for p in 0..h {
            let tau = inp.tau[p];
            for j in 0..a {
                let i = p * a + j;
                out[i] = if (0.0..1.0).contains(&tau) {
                    (self.chunk[i] - inp.x[i]) / (1.0 - tau)
                } else {
                    0.0
                };
            }
        }
        Ok(())
    }
}

/// Encode (trainer) → decode (runtime), every chunk the trainer draws (inside its episode,
/// t ≤ len − H) of `ds` (actions of `width` values) and every slot: the targets lie inside
/// [-1, 1] (min/max groups are never clipped) and decode with `map` against the state of
/// frame t to the dataset's absolute actions (within 1e-5). Returns the largest difference.
pub fn encode_decode_every_chunk(
    ds: &Dataset,
    targets: &Gr00tTargets,
    map: &OutputMap,
    h: usize,
    width: usize,
) -> f32 {
    let (mut chunk, mut reference, mut u) =
        (vec![0f32; h * width], vec![0f32; width], vec![0f32; width]);
    let mut worst = 0f32;
    for (e, ep) in ds.episodes.iter().enumerate() {
        let len = ep.len();
        for t in 0..=len - h {
            for p in 0..h {
                chunk[p * width..(p + 1) * width].copy_from_slice(ep.action((t + p).min(len - 1)));
            }
            targets.encode(e, t, &mut chunk).unwrap();
            assert!(chunk.iter().all(|z| z.abs() <= 1.0), "{chunk:?}");
            map.fill_reference(ep.fast(t), &mut reference);
            for p in 0..h {
                map.decode(&chunk[p * width..(p + 1) * width], p, &reference, &mut u);
                let want = ep.action((t + p).min(len - 1));
                for (j, (x, w)) in u.iter().zip(want).enumerate() {
                    worst = worst.max((x - w).abs());
                    assert!(
                        (x - w).abs() < 1e-5,
                        "episode {e} frame {t} slot {p} dim {j}: decoded {x}, dataset {w}"
                    );
                }
            }
        }
    }
    worst
}

/// Deployed: the lock-step runtime with the run's output map `map`, driven by a head that
/// outputs exactly the trainer's `targets`, replays every episode of `ds` (state and action
/// of `width` values) under πR² async with one- and two-tick calls and πR² without async,
/// and must send, at every tick up to `len − H`, the dataset's action of that tick (within
/// 1e-4): each slot is decoded against the state of the call that made it, the reference
/// training used for it. Returns the largest difference.
pub fn lockstep_sends_the_datasets_actions(
    ds: &Dataset,
    targets: &Gr00tTargets,
    map: &OutputMap,
    emb: &EmbodimentConfig,
    width: usize,
) -> f32 {
    use pir2_runtime::{ActionHead, HeadSpec, LatencyWindow, LockstepDriver, LockstepTiming, Mode};
    use pir2_schedule::{Alignment, FrontMode};
    let h = emb.horizon;
    let pir2_async = |nfe| Mode::PiR2Async {
        nfe,
        alignment: Alignment::Fresh,
        front: FrontMode::Visible,
    };
    let pir2_sync = Mode::PiR2Sync {
        nfe: None,
        alignment: Alignment::Fresh,
        front: FrontMode::Visible,
    };
    let mut worst = 0f32;
    for (mode, call_ticks) in [
        (pir2_async(None), 1),
        (pir2_async(Some(2)), 2),
        (pir2_sync, 2),
    ] {
        for (e, ep) in ds.episodes.iter().enumerate() {
            let states: Vec<Vec<f32>> = (0..ep.len()).map(|t| ep.fast(t).to_vec()).collect();
            let actions: Vec<Vec<f32>> = (0..ep.len()).map(|t| ep.action(t).to_vec()).collect();
            let sp = HeadSpec {
                horizon: h,
                action_dim: width,
                n_obs: emb.n_obs,
                fast_dim: width,
                slow_dim: 0,
                period: PERIOD_NS,
                d_max: emb.d_max,
                d_vis_max: 0,
            };
            let oracle = TargetOracle {
                targets: targets.clone(),
                episode: e,
                states: states.clone(),
                actions: actions.clone(),
                chunk: vec![0.0; h * width],
            };
            let mut head = ActionHead::new(
                oracle,
                sp,
                mode.head_mode(width),
                LatencyWindow::new(20, 0, sp.period, sp.d_max),
                5,
            )
            .unwrap();
            let mut env = Replay {
                width,
                states,
                t: 0,
                sent: Vec::new(),
            };
            let timing = LockstepTiming {
                call_ticks,
                slow_delay: 0,
                overrun_ticks: 0,
                overrun_every: 0,
                pin_delay: true,
            };
            let mut drv = LockstepDriver::new(&head).with_output(map.clone());
            let res = drv
                .run_episode(&mut env, &mut head, &mode, timing, 1, |_, _| {})
                .unwrap();
            assert_eq!(res.steps, ep.len());
            // Ticks up to len − H: every command there comes from chunks made (and rebased)
            // at frames the trainer draws. Later ones may decode a clipped slot: GR00T
            // neither trains on nor takes statistics from chunks that run past the end.
            for (t, sent) in env.sent.iter().enumerate().take(ep.len() + 1 - h) {
                for (j, (x, w)) in sent.iter().zip(&actions[t]).enumerate() {
                    worst = worst.max((x - w).abs());
                    assert!(
                        (x - w).abs() < 1e-4,
                        "{} episode {e} tick {t} dim {j}: sent {x}, dataset {w}",
                        mode.describe()
                    );
                }
            }
        }
    }
    worst
}

/// The LeRobot v3.0 video fixture of pir2-sim (two cameras, real AV1 and H.264 videos).
pub fn video_fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../pir2-sim/tests/fixtures/lerobot_video")
}

/// Copy the directory tree `from` to `to`.
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let p = e.unwrap().path();
        let dst = to.join(p.file_name().unwrap());
        if p.is_dir() {
            copy_dir(&p, &dst);
        } else {
            std::fs::copy(&p, &dst).unwrap();
        }
    }
}

/// The candle head `head` on one call `--record-nfe` recorded (`rec`: the file's tensors, see
/// docs/gr00t-contract.md), returning what it computes from the recorded graph inputs:
/// the DiT tokens `[B, 1 + H, D_in]` from the recorded state and noisy actions (state and action
/// encoders, the delay row added), and the velocity `[B, H, A]` its DiT and decoder give on the
/// recorded DiT inputs (`vl_embs` as the DiT takes them: the backbone side applied `vlln`).
pub fn candle_on_recorded_call(
    head: &pir2_backends::gr00t::n17::Gr00tN17Head,
    rec: &HashMap<String, Tensor>,
    n_obs: usize,
    action_dim: usize,
) -> (Tensor, Tensor) {
    use candle_core::{DType, D};
    use pir2_backends::gr00t::n17::VlTokens;
    let c = head.config();
    let ids = &rec["embodiment_id"];
    let (b, h) = rec["timesteps"].dims2().unwrap();
    let state = rec["state"].reshape((b, n_obs, c.max_state_dim)).unwrap();
    let s = head.encode_state(&state, ids).unwrap();
    let act = head
        .encode_actions(&rec["actions"], &rec["timesteps"], ids)
        .unwrap();
    let act = head.add_delay_embedding(&act, Some(&rec["d_vis"])).unwrap();
    let sa = Tensor::cat(&[&s, &act], 1).unwrap();
    let d_vis = rec["d_vis"].to_dtype(DType::U32).unwrap();
    let vl = VlTokens {
        embeddings: &rec["vl_embs"],
        attention_mask: Some(&rec["backbone_attention_mask"]),
        image_mask: Some(&rec["image_mask"]),
        d_vis: Some(&d_vis),
    };
    let y = head.dit(&rec["sa_embs"], &vl, &rec["timestep"]).unwrap();
    let v = head
        .decode(&y, ids)
        .unwrap()
        .narrow(1, 1, h)
        .unwrap()
        .narrow(D::Minus1, 0, action_dim)
        .unwrap();
    (sa, v)
}

/// `pir2 gr00t run gr00t-xarm-xhand --checkpoint CK --task "catch the book" --emulate
/// --seconds S` with `extra` arguments appended, on the emulators; its exit and output.
pub fn run_emulated_seconds(ck: &Path, seconds: &str, extra: &[&OsStr]) -> (Output, String) {
    let mut args = vec![
        OsStr::new("gr00t"),
        OsStr::new("run"),
        OsStr::new("gr00t-xarm-xhand"),
        OsStr::new("--checkpoint"),
        ck.as_os_str(),
        OsStr::new("--task"),
        OsStr::new("catch the book"),
        OsStr::new("--emulate"),
        OsStr::new("--seconds"),
        OsStr::new(seconds),
    ];
    args.extend_from_slice(extra);
    pir2_text(&args)
}

/// Standard-normal values of `shape` drawn from pir2's seeded generator, so a test's
/// inputs are the same bits on every run (candle's CPU `randn` is not seedable).
pub fn seeded_normal(shape: (usize, usize, usize), seed: u64) -> Tensor {
    let mut rng = pir2_schedule::Rng::new(seed);
    let n = shape.0 * shape.1 * shape.2;
    let v: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}
