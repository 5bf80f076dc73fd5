//! The GR00T-N1.7 xArm6 + XHand stack on tiny synthetic ONNX graphs with the export
//! contract's names and shapes (made in set-up by `pir2_backends::gr00t::testing`, i.e.
//! `make_graphs.py` run with `$PIR2_PYTHON` after `source .native/env.sh`).
//!
//! One file on purpose: every test shares the synthetic checkpoint made once in set-up.
//!
//! Covers: the action head's delay embedding and per-position timesteps, contract violations
//! (wrong name, rank, dim, type, missing statistic, delay-table shape), and the whole stack
//! end to end through the real-time driver at 25 Hz on the xArm6 + XHand emulators.
#![cfg(feature = "gr00t")]

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use pir2_backends::gr00t::weights::{write_f32, DELAY_EMBEDDING};
use pir2_backends::gr00t::{
    run_gr00t_report, CheckpointFiles, Gr00tActionHead, Gr00tBackbone, Gr00tRunOptions, Normalizer,
    VocabTokenizer,
};
use pir2_backends::ort::OrtOptions;
use pir2_runtime::{Clock, ModelInput, SlowFrame, SlowInput, SystemClock, VelocityModel};

use pir2_backends::gr00t::testing::{
    python_from_env, statistics_json, tiny_embodiment as embodiment, write_tiny_checkpoint,
    SyntheticCamera, D_IN, D_VL,
};

/// A checkpoint directory with graphs (`variant` breaks one of them) and side files.
fn fixture(name: &str, variant: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("pir2-gr00t-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let python = python_from_env().unwrap();
    write_tiny_checkpoint(&dir, variant, &python).unwrap();
    dir
}

fn load_head(dir: &Path) -> pir2_backends::Result<Gr00tActionHead> {
    load_head_as(dir, embodiment())
}

fn load_head_as(
    dir: &Path,
    cfg: pir2_backends::gr00t::EmbodimentConfig,
) -> pir2_backends::Result<Gr00tActionHead> {
    let files = CheckpointFiles::in_dir(dir);
    let norm = Normalizer::load(&files.statistics, &cfg)?;
    Gr00tActionHead::load(&files, &cfg, norm, 3, &OrtOptions::default())
}

fn call(head: &mut Gr00tActionHead, tau: &[f32], d_vis: u32, vl: &[f32]) -> Vec<f32> {
    let (h, a) = (50, 18);
    let x: Vec<f32> = (0..h * a)
        .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
        .collect();
    let obs: Vec<f32> = (0..45).map(|i| (i as f32 * 0.1).sin()).collect();
    let dv = [d_vis];
    let input = ModelInput {
        batch: 1,
        horizon: h,
        action_dim: a,
        x: &x,
        tau,
        obs_fast: &obs,
        n_obs: 1,
        fast_dim: 45,
        slow: SlowInput::Tokens {
            data: vl,
            tokens: 8,
            dim: D_VL,
        },
        d_vis: &dv,
    };
    let mut v = vec![0.0; h * a];
    head.velocity(&input, &mut v).unwrap();
    v
}

/// A state group with GR00T's sin/cos encoding enters the model twice as wide: the head's
/// state width grows by the group's width, the output changes, and a graph whose padded
/// state width is too small for the encoded state is refused naming both widths.
#[test]
fn a_sin_cos_state_group_widens_the_models_state_and_is_checked_against_the_graph() {
    use pir2_backends::gr00t::Norm;
    let dir = fixture("sincos", "");
    let vl: Vec<f32> = (0..8 * D_VL).map(|i| (i as f32 * 0.37).cos()).collect();
    let tau: Vec<f32> = (0..50).map(|p| 1.0 - p as f32 / 50.0).collect();
    let layout = || pir2_backends::gr00t::VlLayout {
        image_mask: (0..8).map(|i| i < 4).collect(),
        attention_mask: vec![true; 8],
    };
    let mut plain = load_head(&dir).unwrap();
    plain.set_vl_layout(layout());
    let v_plain = call(&mut plain, &tau, 0, &vl);

    let mut cfg = embodiment();
    assert_eq!(cfg.state[0].name, "arm_joints");
    cfg.state[0].norm = Norm::SinCos;
    let mut sc = load_head_as(&dir, cfg.clone()).unwrap();
    assert_eq!(sc.dims().state_dim, 45);
    assert_eq!(sc.dims().encoded_state_dim, 51);
    sc.set_vl_layout(layout());
    let v_sc = call(&mut sc, &tau, 0, &vl);
    assert!(v_sc.iter().all(|x| x.is_finite()));
    assert_ne!(v_plain, v_sc, "the encoding did not reach the state tokens");

    // Every group encoded: 90 values per step, more than the graph's 64.
    for g in cfg.state.iter_mut() {
        g.norm = Norm::SinCos;
    }
    let e = load_head_as(&dir, cfg).unwrap_err().to_string();
    assert!(
        e.contains("max_state_dim >= 90") && e.contains("after sin/cos encoding; 45 raw"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn delay_embedding_row_and_per_position_timesteps_reach_the_output() {
    let dir = fixture("head", "");
    let mut head = load_head(&dir).unwrap();
    assert_eq!(head.dims().d_in, D_IN);
    assert_eq!(head.dims().max_state_dim, 64);
    head.set_vl_layout(pir2_backends::gr00t::VlLayout {
        image_mask: (0..8).map(|i| i < 4).collect(),
        attention_mask: vec![true; 8],
    });
    let vl: Vec<f32> = (0..8 * D_VL).map(|i| (i as f32 * 0.37).cos()).collect();
    let tau: Vec<f32> = (0..50).map(|p| 1.0 - p as f32 / 50.0).collect();

    // Zero-initialised table: every d_vis gives the no-delay output, bit for bit.
    let v0 = call(&mut head, &tau, 0, &vl);
    assert_eq!(v0, call(&mut head, &tau, 3, &vl));
    // A known row changes the output for that d_vis only.
    let row: Vec<f32> = (0..D_IN).map(|j| 0.5 * ((j as f32) * 0.9).sin()).collect();
    head.set_delay_row(3, &row).unwrap();
    let v3 = call(&mut head, &tau, 3, &vl);
    let diff: f32 = v0.iter().zip(&v3).map(|(a, b)| (a - b).abs()).sum();
    assert!(diff > 1e-3, "row 3 did not change the output ({diff})");
    assert_eq!(v0, call(&mut head, &tau, 2, &vl));
    // d_vis beyond the table is clamped to d_vis_max (row 5 is zero).
    assert_eq!(v0, call(&mut head, &tau, 9, &vl));
    assert_eq!(head.d_vis_counts(), &[1, 0, 1, 2, 0, 1]);

    // Per-position timesteps: changing τ at position 7 changes the velocity at 7 only.
    let mut tau2 = tau.clone();
    tau2[7] = 0.0;
    let v7 = call(&mut head, &tau2, 0, &vl);
    for p in 0..50 {
        let same = v0[p * 18..(p + 1) * 18] == v7[p * 18..(p + 1) * 18];
        assert_eq!(same, p != 7, "position {p}");
    }
    // The backbone tokens reach the output.
    let vl2: Vec<f32> = vl.iter().map(|x| x + 0.5).collect();
    assert_ne!(v0, call(&mut head, &tau, 0, &vl2));
    std::fs::remove_dir_all(&dir).ok();
}

fn load_err(variant: &str) -> String {
    let dir = fixture(variant, variant);
    let e = load_head(&dir).unwrap_err().to_string();
    std::fs::remove_dir_all(&dir).ok();
    eprintln!("{variant}: {e}");
    e
}

#[test]
fn contract_violations_name_the_file_and_the_tensor() {
    let e = load_err("wrong_name");
    assert!(
        e.contains("dit.onnx") && e.contains("`sa_emb`") && e.contains("unexpected input"),
        "{e}"
    );
    let e = load_err("wrong_rank");
    assert!(
        e.contains("action_encoder.onnx") && e.contains("`timesteps`") && e.contains("rank 1"),
        "{e}"
    );
    let e = load_err("wrong_dim");
    assert!(
        e.contains("dit.onnx")
            && e.contains("`sa_embs`")
            && e.contains("D_in")
            && e.contains("state_encoder.onnx"),
        "{e}"
    );
    let e = load_err("wrong_type");
    assert!(
        e.contains("action_decoder.onnx") && e.contains("`output`") && e.contains("float32"),
        "{e}"
    );

    // A missing statistic, a missing file, and a delay table of the wrong shape.
    let dir = fixture("files", "");
    let cfg = embodiment();
    std::fs::write(
        dir.join("statistics.json"),
        statistics_json(&cfg, Some("state.fingertip_forces.min")),
    )
    .unwrap();
    let e = load_head(&dir).unwrap_err().to_string();
    assert!(
        e.contains("statistics.json")
            && e.contains("new_embodiment.state.fingertip_forces.min")
            && e.contains("missing"),
        "{e}"
    );
    std::fs::write(dir.join("statistics.json"), statistics_json(&cfg, None)).unwrap();
    write_f32(
        &dir.join("pir2_gr00t.safetensors"),
        &[(DELAY_EMBEDDING, vec![5, D_IN], vec![0.0; 5 * D_IN])],
    )
    .unwrap();
    let e = load_head(&dir).unwrap_err().to_string();
    assert!(
        e.contains("pir2_gr00t.safetensors")
            && e.contains(DELAY_EMBEDDING)
            && e.contains("[6, 32]"),
        "{e}"
    );
    std::fs::remove_file(dir.join("onnx/dit.onnx")).unwrap();
    let e = load_head(&dir).unwrap_err().to_string();
    assert!(e.contains("dit.onnx") && e.contains("DiT"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}

/// The backbone of `files` with its `vocab.txt` tokenizer and the prompt "catch the book",
/// checked against a DiT of width `d_vl`.
fn vocab_backbone(
    files: &CheckpointFiles,
    cfg: &pir2_backends::gr00t::EmbodimentConfig,
    d_vl: usize,
) -> pir2_backends::Result<Gr00tBackbone> {
    let tok = VocabTokenizer::load(&files.vocab)?;
    Gr00tBackbone::load(
        files,
        &cfg.image,
        &cfg.prompt,
        &cfg.vision,
        &tok,
        "catch the book",
        Some((d_vl, PathBuf::from("dit.onnx"))),
        &OrtOptions::default(),
    )
}

#[test]
fn backbone_encodes_camera_frames_into_tokens() {
    let dir = fixture("backbone", "");
    let files = CheckpointFiles::in_dir(&dir);
    let cfg = embodiment();
    let mut bb = vocab_backbone(&files, &cfg, D_VL).unwrap();
    assert_eq!(bb.output_shape(), (8, D_VL));
    assert_eq!(bb.sequence().ids, vec![2, 2, 2, 2, 3, 4, 5, 0]);
    let a = bb
        .encode_image(&vec![10u8; 480 * 640 * 3], (480, 640))
        .unwrap()
        .to_vec();
    let b = bb
        .encode_image(&vec![200u8; 480 * 640 * 3], (480, 640))
        .unwrap()
        .to_vec();
    assert_eq!(a.len(), 8 * D_VL);
    assert_ne!(a, b, "the image reaches the features");
    // A backbone width that disagrees with the DiT is a contract error naming both.
    let e = vocab_backbone(&files, &cfg, D_VL + 1)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("backbone.onnx") && e.contains("D_vl") && e.contains("dit.onnx"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn backbone_takes_one_image_per_camera_view_in_view_order() {
    use pir2_runtime::{SlowEncoder, View};
    let dir = fixture("views", "");
    let files = CheckpointFiles::in_dir(&dir);
    let mut cfg = embodiment();
    cfg.prompt.chat.images = 2;
    let mut bb = vocab_backbone(&files, &cfg, D_VL).unwrap();
    assert_eq!(bb.views(), 2);
    let view = |v: u8, (h, w): (usize, usize)| View {
        image: (0..h * w * 3)
            .map(|i| v.wrapping_add((i % 7) as u8))
            .collect(),
        hw: (h, w),
    };
    // Two cameras of different sizes: each view is preprocessed on its own.
    let (top, wrist) = (view(10, (480, 640)), view(200, (240, 320)));
    let a = bb
        .encode_views(&[top.clone(), wrist.clone()])
        .unwrap()
        .to_vec();
    assert_eq!(a.len(), 8 * D_VL);
    let swapped = bb
        .encode_views(&[wrist.clone(), top.clone()])
        .unwrap()
        .to_vec();
    assert_ne!(a, swapped, "the view order reaches the features");
    let other = bb
        .encode_views(&[top.clone(), view(90, (240, 320))])
        .unwrap()
        .to_vec();
    assert_ne!(a, other, "the second view reaches the features");
    // Through the slow channel's encoder trait: the frame's views, in order.
    let frame = SlowFrame {
        t_capture: 7,
        views: vec![top.clone(), wrist.clone()],
        ..Default::default()
    };
    let f = pir2_runtime::realtime::block_on(bb.encode(frame)).unwrap();
    assert_eq!((f.t_capture, f.tokens, f.dim), (7, 8, D_VL));
    assert_eq!(f.data, a);
    // A frame with another number of views is one error naming both counts and the config.
    let e = bb.encode_views(&[top]).unwrap_err().to_string();
    assert!(
        e.contains("camera views") && e.contains('2') && e.contains("prompt.chat.images"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn backbone_with_tokenizer_json_feeds_gr00ts_chat_template() {
    use pir2_backends::gr00t::testing::{add_bpe_tokenizer, BPE_TEXT_TOKENS};
    use pir2_backends::gr00t::{load_tokenizer, EmbodimentConfig};

    let dir = fixture("bpe", "");
    add_bpe_tokenizer(&dir).unwrap();
    let files = CheckpointFiles::in_dir(&dir);
    let cfg = EmbodimentConfig::load(&files.embodiment).unwrap();
    let tok = load_tokenizer(&files, &cfg.prompt).unwrap();
    assert!(
        tok.chat_template().is_some(),
        "tokenizer.json is preferred to vocab.txt"
    );
    let load = |prompt: &str| {
        Gr00tBackbone::load(
            &files,
            &cfg.image,
            &cfg.prompt,
            &cfg.vision,
            tok.as_ref(),
            prompt,
            Some((D_VL, PathBuf::from("dit.onnx"))),
            &OrtOptions::default(),
        )
        .unwrap()
    };
    let mut bb = load("Catch the book!");
    let t = 4 + BPE_TEXT_TOKENS;
    assert_eq!(bb.output_shape(), (t, D_VL));
    // Python `tokenizers` on the fixture: <|im_start|> user \n <|vision_start|> <|image_pad|>×4
    // <|vision_end|> catch the book <|im_end|> \n, left-padded with <|endoftext|> (400).
    let want = [
        401, 379, 198, 403, 405, 405, 405, 405, 404, 336, 291, 258, 316, 402, 198,
    ];
    let s = bb.sequence().clone();
    let pad = t - want.len();
    assert_eq!(&s.ids[pad..], &want);
    assert!(s.ids[..pad].iter().all(|&i| i == 400));
    assert_eq!(s.attention.iter().sum::<i64>(), want.len() as i64);
    let image: Vec<usize> = (0..t).filter(|&i| s.layout.image_mask[i]).collect();
    assert_eq!(image, (pad + 4..pad + 8).collect::<Vec<_>>());
    let img = vec![90u8; 480 * 640 * 3];
    let a = bb.encode_image(&img, (480, 640)).unwrap().to_vec();
    let b = load("put the ball in the bowl")
        .encode_image(&img, (480, 640))
        .unwrap()
        .to_vec();
    assert_eq!(a.len(), t * D_VL);
    assert_ne!(a, b, "the prompt's ids reach the features");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn end_to_end_25hz_on_the_emulated_xarm6_xhand() {
    use pir2_robots::emu::{EmulatedArmHand, EmulatedArmHandConfig};
    use pir2_robots::split;

    let dir = fixture("e2e", "");
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let (emu, layer) =
        EmulatedArmHand::start(&EmulatedArmHandConfig::default(), clock.clone()).unwrap();
    let (source, actuator) = split(layer);

    let camera = SyntheticCamera::new(clock.clone(), Duration::from_millis(60));
    let frames = camera.frames();
    let ticks = 50; // 2 s at 25 Hz
    let opts = Gr00tRunOptions {
        max_ticks: Some(ticks),
        clock: clock.clone(),
        warm_start_steps: 2,
        ..Default::default()
    };
    let report = run_gr00t_report(&dir, "catch_book", source, actuator, camera, opts).unwrap();
    let m = &report.metrics;
    let lat = m.call_latency.summary();
    eprintln!(
        "ticks {} calls {} swaps {} overruns {} call p50 {} µs p99 {} µs; d {:?}; d_vis {:?}; model d_vis counts {:?}; frames {}",
        m.ticks,
        m.calls.len(),
        m.swaps,
        m.overruns,
        lat.p50 / 1000,
        lat.p99 / 1000,
        m.calls.iter().map(|c| c.d).collect::<Vec<_>>(),
        m.calls.iter().map(|c| c.d_vis).collect::<Vec<_>>(),
        report.d_vis_counts,
        frames.load(Ordering::Relaxed)
    );
    assert_eq!(report.prompt, "catch the book");
    assert_eq!(m.ticks, ticks);
    // The action head ran on the worker and its chunks reached the robot.
    assert!(
        !m.calls.is_empty() && m.swaps >= 1,
        "calls {} swaps {}",
        m.calls.len(),
        m.swaps
    );
    assert!(emu.hand_commands() >= ticks);
    // The backbone refreshed the cache more than once while the robot ran.
    assert!(frames.load(Ordering::Relaxed) >= 3);
    // Every call's d_vis is within the table, and each reached the delay embedding.
    assert!(m.calls.iter().all(|c| c.d_vis <= 5));
    for k in 0..=5 {
        let recorded = m.calls.iter().filter(|c| c.d_vis == k).count() as u64;
        assert!(
            report.d_vis_counts[k] >= recorded,
            "d_vis {k}: model saw {} < recorded {recorded}",
            report.d_vis_counts[k]
        );
    }
    // Cached features age between frames (60 ms capture period > one 40 ms tick).
    assert!(
        m.calls.iter().any(|c| c.d_vis >= 1),
        "{:?}",
        m.calls.iter().map(|c| c.d_vis).collect::<Vec<_>>()
    );
    drop(emu);
    std::fs::remove_dir_all(&dir).ok();
}

/// The FakeRobot's `[q, q − cmd]` (36-d) laid out as the 45-d xArm6 + XHand state: arm
/// joints, hand joints, hand "torques" (tracking error), zero fingertip forces.
struct State45(pir2_runtime::testing::FakeRobot, [f32; 36]);

impl pir2_runtime::FastSource for State45 {
    fn dim(&self) -> usize {
        45
    }
    fn read(&mut self, out: &mut [f32]) -> pir2_runtime::Result<pir2_runtime::Nanos> {
        let t = self.0.read(&mut self.1)?;
        out[..18].copy_from_slice(&self.1[..18]);
        out[18..30].copy_from_slice(&self.1[24..36]);
        out[30..].fill(0.0);
        Ok(t)
    }
}

/// A stand-in for a remote backbone: tokens computed from the frame's values.
struct TokenEncoder {
    encoded: Arc<AtomicU64>,
}

#[async_trait::async_trait]
impl pir2_runtime::SlowEncoder for TokenEncoder {
    async fn encode(
        &mut self,
        frame: SlowFrame,
    ) -> pir2_runtime::Result<pir2_runtime::SlowFeatures> {
        self.encoded.fetch_add(1, Ordering::Relaxed);
        let v = frame.values.first().copied().unwrap_or(0.0);
        Ok(pir2_runtime::SlowFeatures {
            t_capture: frame.t_capture,
            data: (0..8 * D_VL)
                .map(|i| (v * 0.1 + i as f32 * 0.01).sin())
                .collect(),
            tokens: 8,
            dim: D_VL,
        })
    }
}

#[test]
fn custom_backbone_seam_drives_the_head_on_a_fake_robot() {
    use pir2_backends::gr00t::{run_gr00t, BackboneChoice, VlLayout};
    use pir2_runtime::testing::{CameraStub, FakeRobot};

    let dir = fixture("custom", "");
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let robot = FakeRobot::new(18, clock.clone());
    let sent = robot.sent.clone();
    let encoded = Arc::new(AtomicU64::new(0));
    let opts = Gr00tRunOptions {
        max_ticks: Some(25),
        clock: clock.clone(),
        warm_start_steps: 2,
        backbone: BackboneChoice::Custom {
            encoder: Box::new(TokenEncoder {
                encoded: encoded.clone(),
            }),
            layout: VlLayout {
                image_mask: (0..8).map(|i| i < 4).collect(),
                attention_mask: vec![true; 8],
            },
        },
        ..Default::default()
    };
    let camera = CameraStub::new(clock.clone(), Duration::from_millis(50), 1);
    let m = run_gr00t(
        &dir,
        "put the box in the basket",
        State45(robot.clone(), [0.0; 36]),
        robot,
        camera,
        opts,
    )
    .unwrap();
    assert_eq!(m.ticks, 25);
    assert_eq!(sent.load(Ordering::Relaxed), 25);
    assert!(!m.calls.is_empty());
    assert!(encoded.load(Ordering::Relaxed) >= 2);

    // A layout whose length disagrees with the features is refused before the robot moves.
    let robot = FakeRobot::new(18, clock.clone());
    let opts = Gr00tRunOptions {
        max_ticks: Some(5),
        clock: clock.clone(),
        backbone: BackboneChoice::Custom {
            encoder: Box::new(TokenEncoder {
                encoded: Arc::new(AtomicU64::new(0)),
            }),
            layout: VlLayout {
                image_mask: vec![true; 3],
                attention_mask: vec![true; 2],
            },
        },
        ..Default::default()
    };
    let camera = CameraStub::new(clock.clone(), Duration::from_millis(10), 1);
    let e = run_gr00t(
        &dir,
        "catch_book",
        State45(robot.clone(), [0.0; 36]),
        robot.clone(),
        camera,
        opts,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("VL layout"), "{e}");
    assert_eq!(robot.sent.load(Ordering::Relaxed), 0);
    std::fs::remove_dir_all(&dir).ok();
}

/// A camera that delivers `frames` frames, then stalls (a dead camera or slow server).
struct StallingCamera {
    inner: pir2_runtime::testing::CameraStub,
    frames: u32,
}

#[async_trait::async_trait]
impl pir2_runtime::SlowSource for StallingCamera {
    async fn capture(&mut self) -> pir2_runtime::Result<SlowFrame> {
        if self.frames == 0 {
            std::thread::sleep(Duration::from_secs(30));
        }
        self.frames -= 1;
        self.inner.capture().await
    }
}

/// The stale-slow stop is on by default in `run_gr00t`: when the camera stalls, the robot is
/// stopped with a safety stop within `(d_vis_max + ½)·T + grace` instead of acting on the
/// last image until the end of the run (before: the grace was never set, `d_vis` was clamped
/// to `d_vis_max` and the run went on for all its ticks). A longer grace lets it run longer.
#[test]
fn a_stalled_camera_stops_the_robot_within_the_stale_slow_grace() {
    use pir2_backends::gr00t::{run_gr00t, BackboneChoice, VlLayout};
    use pir2_runtime::testing::{CameraStub, FakeRobot};

    let dir = fixture("stale", "");
    let go = |grace: Option<Duration>| {
        let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
        let robot = FakeRobot::new(18, clock.clone());
        let (sent, stops) = (robot.sent.clone(), robot.stops.clone());
        let opts = Gr00tRunOptions {
            // 1000 ticks at 25 Hz: 40 s if nothing stops the run.
            max_ticks: Some(1000),
            clock: clock.clone(),
            warm_start_steps: 2,
            slow_grace: grace,
            backbone: BackboneChoice::Custom {
                encoder: Box::new(TokenEncoder {
                    encoded: Arc::new(AtomicU64::new(0)),
                }),
                layout: VlLayout {
                    image_mask: (0..8).map(|i| i < 4).collect(),
                    attention_mask: vec![true; 8],
                },
            },
            ..Default::default()
        };
        let camera = StallingCamera {
            inner: CameraStub::new(clock.clone(), Duration::from_millis(40), 1),
            frames: 5,
        };
        let t0 = std::time::Instant::now();
        let r = run_gr00t(
            &dir,
            "catch_book",
            State45(robot.clone(), [0.0; 36]),
            robot,
            camera,
            opts,
        );
        (
            r,
            t0.elapsed(),
            sent.load(Ordering::Relaxed),
            stops.load(Ordering::Relaxed),
        )
    };
    let (r, took, sent, stops) = go(None);
    let e = format!("{:#}", r.expect_err("a stalled camera must stop the run"));
    assert!(e.contains("slow features are"), "{e}");
    assert!(stops >= 1, "the robot was not stopped");
    // 5 frames (~0.2 s), then (d_vis_max + ½)·40 ms + 200 ms; well under the run's 40 s.
    assert!(took < Duration::from_secs(5), "stopped after {took:?}");
    assert!(sent < 125, "sent {sent} commands");

    let (r, took_long, _, _) = go(Some(Duration::from_millis(1500)));
    let e = format!("{:#}", r.expect_err("a stalled camera must stop the run"));
    assert!(e.contains("1500.0 ms grace"), "{e}");
    assert!(
        took_long > took + Duration::from_millis(1000),
        "{took_long:?} vs {took:?}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// Counts the calls it forwards (a stand-in for a remote action-head client).
struct Forward<M> {
    inner: M,
    calls: Arc<AtomicU64>,
}

impl<M: pir2_runtime::VelocityModel> pir2_runtime::VelocityModel for Forward<M> {
    fn backend(&self) -> &'static str {
        "forward"
    }
    fn velocity(
        &mut self,
        input: &pir2_runtime::ModelInput<'_>,
        out: &mut [f32],
    ) -> pir2_runtime::Result<()> {
        self.calls.fetch_add(1, Ordering::Relaxed);
        self.inner.velocity(input, out)
    }
}

#[test]
fn custom_head_seam_drives_a_forwarded_head_on_a_fake_robot() {
    use pir2_backends::gr00t::{load_action_head, run_gr00t_report, HeadChoice};
    use pir2_backends::ort::OrtOptions;
    use pir2_runtime::testing::FakeRobot;

    let dir = fixture("custom-head", "");
    let (head, prompt) = load_action_head(&dir, "catch_book", &OrtOptions::default()).unwrap();
    assert_eq!(prompt, "catch the book");
    let d_vl = head.dims().d_vl;
    let calls = Arc::new(AtomicU64::new(0));
    let clock: Arc<dyn Clock> = Arc::new(SystemClock::new());
    let robot = FakeRobot::new(18, clock.clone());
    let sent = robot.sent.clone();
    let opts = Gr00tRunOptions {
        max_ticks: Some(25),
        clock: clock.clone(),
        warm_start_steps: 2,
        head: HeadChoice::Custom {
            model: Box::new(Forward {
                inner: head,
                calls: calls.clone(),
            }),
            d_vl,
        },
        ..Default::default()
    };
    // The checkpoint's ONNX backbone on the synthetic camera; the head behind the seam.
    let camera = SyntheticCamera::new(clock.clone(), Duration::from_millis(60));
    let report = run_gr00t_report(
        &dir,
        "catch_book",
        State45(robot.clone(), [0.0; 36]),
        robot,
        camera,
        opts,
    )
    .unwrap();
    let m = &report.metrics;
    assert_eq!(m.ticks, 25);
    assert_eq!(sent.load(Ordering::Relaxed), 25);
    assert!(!m.calls.is_empty());
    // Every model call went through the seam and was counted per d_vis.
    let n = calls.load(Ordering::Relaxed);
    assert!(n >= m.calls.len() as u64, "{n} < {}", m.calls.len());
    assert_eq!(report.d_vis_counts.iter().sum::<u64>(), n);

    // A custom head whose D_vl disagrees with the backbone is refused before the robot moves.
    let (head, _) = load_action_head(&dir, "catch_book", &OrtOptions::default()).unwrap();
    let robot = FakeRobot::new(18, clock.clone());
    let opts = Gr00tRunOptions {
        max_ticks: Some(5),
        clock: clock.clone(),
        head: HeadChoice::Custom {
            model: Box::new(head),
            d_vl: d_vl + 1,
        },
        ..Default::default()
    };
    let camera = SyntheticCamera::new(clock.clone(), Duration::from_millis(60));
    let e = run_gr00t_report(
        &dir,
        "catch_book",
        State45(robot.clone(), [0.0; 36]),
        robot.clone(),
        camera,
        opts,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("D_vl"), "{e}");
    assert_eq!(robot.sent.load(Ordering::Relaxed), 0);
    std::fs::remove_dir_all(&dir).ok();
}
