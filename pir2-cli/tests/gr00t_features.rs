//! `pir2 gr00t features` on a tiny LeRobotDataset v3.0 with camera videos (the committed
//! fixture `pir2-sim/tests/fixtures/lerobot_video`, made by `make_lerobot_video.py` with PyAV:
//! 2 episodes of 5 and 7 frames, an AV1 and an H.264 view of 32×24 px, episodes concatenated
//! in one file per view): the frames pir2 decodes equal PyAV's (LeRobot's decoding backend)
//! under LeRobot's timestamp rule; the features file holds, row for row, what the backbone
//! gives on those frames, agrees with the deployment path, is accepted by `pir2 gr00t train`,
//! and an interrupted run resumes to the same bytes. An image-typed camera (PNG/JPEG in the
//! data file) added to a copy of the fixture decodes as Pillow does. Needs `ffmpeg` and
//! `$PIR2_PYTHON` with `av`, `onnx`, `pillow` and `pyarrow` (scripts/setup-native.sh;
//! `source .native/env.sh`).
//!
//! One file on purpose: the tests share the fixture, the tiny checkpoints and the Python
//! references built at its top.
#![cfg(feature = "gr00t")]

use std::ffi::OsString;
use std::path::Path;
use std::process::Command;

use pir2_backends::gr00t::n17::train::PrecomputedFeatures;
use pir2_backends::gr00t::testing::{
    add_bpe_tokenizer, python_from_env, write_split_backbone, write_tiny_checkpoint,
    write_tiny_checkpoint_with_width,
};
use pir2_backends::gr00t::{
    load_tokenizer, CheckpointFiles, EmbodimentConfig, Gr00tBackbone, PromptTokenizer,
};
use pir2_backends::ort::OrtOptions;
use pir2_cli::study::gr00t::features::{
    extract, partial_path, progress_path, Gr00tFeaturesOptions,
};
use pir2_sim::dataset::{ffmpeg_program, FrameReader, VideoDataset, DEFAULT_TOLERANCE_S};

mod common;
use common::gr00t::{
    alt_checkpoint, arm_grip_embodiment, pir2, read_json, run_python, state_and_action, text,
    train_args,
};
use common::gr00t::{copy_dir, video_fixture as fixture};
use common::Scratch;

const VIEWS: [&str; 2] = ["observation.images.front", "observation.images.wrist"];
/// `D_vl` of the training fixture `alt` (pir2-backends/tests/fixtures/gr00t_n17_head).
const D_VL: usize = common::gr00t::ALT_D_VL;

/// PyAV the way LeRobot decodes (`decode_video_frames_pyav`): every frame's time is
/// `pts · time_base`, the frame for a query is the nearest one and must lie within the
/// tolerance; `frame.to_ndarray(format="rgb24")`.
const PYAV_REF: &str = r#"
import json, sys
import av, numpy as np
q = json.load(open(sys.argv[1]))
out = open(sys.argv[2], "wb")
meta = []
for item in q:
    c = av.open(item["file"]); st = c.streams.video[0]
    frames, ts = [], []
    for f in c.decode(st):
        frames.append(f.to_ndarray(format="rgb24")); ts.append(float(f.pts * st.time_base))
    c.close()
    ts = np.array(ts)
    for t in item["times"]:
        d = np.abs(ts - t); i = int(d.argmin())
        assert d[i] < item["tol"], (t, ts)
        out.write(frames[i].tobytes()); meta.append([float(ts[i])] + list(frames[i].shape))
json.dump(meta, open(sys.argv[2] + ".json", "w"))
"#;

#[test]
fn decoded_frames_equal_pyav_under_lerobots_timestamp_rule() {
    let dir = Scratch::new("gr00t-features-decode");
    let python = python_from_env().unwrap();
    let data = VideoDataset::open(&fixture()).unwrap();
    assert_eq!(data.total_frames(), 12);
    assert_eq!(data.video_keys, VIEWS);
    assert_eq!(data.tasks, ["pick the cube", "Put the ball in the bowl!"]);
    assert_eq!(data.task(&data.episodes[1], 3), "Put the ball in the bowl!");
    data.check_views(&VIEWS.map(String::from)).unwrap();
    let e = data
        .check_views(&["observation.images.top".to_string()])
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("observation.images.top") && e.contains(VIEWS[0]),
        "{e}"
    );

    let mut queries = Vec::new();
    let mut ours: Vec<u8> = Vec::new();
    let mut times = Vec::new();
    for key in VIEWS {
        let mut reader = FrameReader::new(ffmpeg_program(), DEFAULT_TOLERANCE_S);
        let mut q = Vec::new();
        for ep in &data.episodes {
            for t in 0..ep.len() {
                let time = ep.videos[key].from_timestamp + ep.timestamps[t];
                let f = reader.frame(&data, key, ep, t).unwrap();
                assert_eq!(f.hw, (24, 32));
                ours.extend_from_slice(&f.rgb);
                times.push(f.time);
                q.push(time);
            }
        }
        let file = data.video_file(key, &data.episodes[0]).unwrap();
        queries.push(serde_json::json!({"file": file, "times": q, "tol": DEFAULT_TOLERANCE_S}));
    }
    let qpath = dir.path().join("queries.json");
    std::fs::write(&qpath, serde_json::to_string(&queries).unwrap()).unwrap();
    let rpath = dir.path().join("pyav.raw");
    run_python(
        &python,
        &dir.path().join("pyav_ref.py"),
        PYAV_REF,
        &[qpath.as_os_str(), rpath.as_os_str()],
        "PyAV reference",
    );
    let theirs = std::fs::read(&rpath).unwrap();
    let meta: Vec<Vec<f64>> =
        serde_json::from_value(read_json(&rpath.with_extension("raw.json"))).unwrap();
    assert_eq!(ours.len(), theirs.len());
    assert_eq!(meta.len(), times.len());
    for (m, t) in meta.iter().zip(&times) {
        assert!((m[0] - t).abs() < 1e-9, "frame time {t} vs PyAV {}", m[0]);
    }
    let max = ours
        .iter()
        .zip(&theirs)
        .map(|(a, b)| a.abs_diff(*b))
        .max()
        .unwrap();
    let differ = ours.iter().zip(&theirs).filter(|(a, b)| a != b).count();
    println!(
        "pir2 (ffmpeg) vs PyAV: {} bytes, max |diff| = {max}, {differ} differ",
        ours.len()
    );
    assert!(max <= 1, "max |pir2 − PyAV| = {max} (> 1/255)");
    // Both views, both episodes: the frames differ (the reader does not repeat one frame).
    let n = 24 * 32 * 3;
    assert_ne!(&ours[..n], &ours[n..2 * n]);
    assert_ne!(&ours[..n], &ours[12 * n..13 * n]);

    // A frame that is not in the video: one error naming the file, the episode and the frame.
    let mut shifted = data.clone();
    shifted.episodes[1].timestamps[6] += 0.05;
    let mut reader = FrameReader::new(ffmpeg_program(), DEFAULT_TOLERANCE_S);
    let ep = &shifted.episodes[1];
    for t in 0..6 {
        reader.frame(&shifted, VIEWS[1], ep, t).unwrap();
    }
    let e = reader
        .frame(&shifted, VIEWS[1], ep, 6)
        .unwrap_err()
        .to_string();
    println!("{e}");
    assert!(
        e.contains("file-000.mp4") && e.contains("episode 1, frame 6") && e.contains("nearest"),
        "{e}"
    );
    // No decoder: one error naming the program and FFmpeg.
    let mut reader = FrameReader::new(dir.path().join("no-ffmpeg"), DEFAULT_TOLERANCE_S);
    let e = reader
        .frame(&data, VIEWS[0], &data.episodes[0], 0)
        .unwrap_err()
        .to_string();
    println!("{e}");
    assert!(e.contains("no-ffmpeg") && e.contains("FFmpeg"), "{e}");
}

/// The training test's embodiment (4 state values, 4 actions, n_obs = 2, slot 1) with
/// H = 7, so that the fixture's longer episode (7 frames) holds one whole chunk (the trainer
/// draws only chunks inside an episode, as GR00T does), the tiny backbone's image and prompt
/// and the fixture's two camera views.
fn embodiment() -> EmbodimentConfig {
    let mut e = arm_grip_embodiment(7, 3);
    e.image.shortest_edge = 16;
    e.image.resize = 16;
    e.image.crop = 16;
    e.prompt.image_tokens = 4;
    e.prompt.text_tokens = 4;
    e.prompt.chat.images = 2;
    e.cameras = VIEWS.map(String::from).to_vec();
    e
}

/// The backbone of the checkpoint `files` under `cfg` with the prompt `prompt`.
fn backbone(
    files: &CheckpointFiles,
    cfg: &EmbodimentConfig,
    tok: &dyn PromptTokenizer,
    prompt: &str,
) -> Gr00tBackbone {
    Gr00tBackbone::load(
        files,
        &cfg.image,
        &cfg.prompt,
        &cfg.vision,
        tok,
        prompt,
        None,
        &OrtOptions::default(),
    )
    .unwrap()
}

/// The `embeddings` of a features file as `n` rows of `width` values.
fn embedding_rows(feats: &Path, n: usize, width: usize) -> Vec<Vec<f32>> {
    let tensors = candle_core::safetensors::load(feats, &candle_core::Device::Cpu).unwrap();
    tensors["embeddings"]
        .to_dtype(candle_core::DType::F32)
        .unwrap()
        .reshape((n, width))
        .unwrap()
        .to_vec2()
        .unwrap()
}

fn layer_norm(x: &[f32]) -> Vec<f32> {
    let d = x.len() as f32;
    let mean = x.iter().sum::<f32>() / d;
    let var = x.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / d;
    x.iter().map(|v| (v - mean) / (var + 1e-5).sqrt()).collect()
}

#[test]
fn features_are_the_backbone_on_the_decoded_frames_and_train_accepts_them() {
    let dir = Scratch::new("gr00t-features");
    let root = dir.path();
    let python = python_from_env().unwrap();
    let (data_dir, ck, emb, feats) = (
        root.join("data"),
        root.join("ck"),
        root.join("embodiment.toml"),
        root.join("features.safetensors"),
    );
    copy_dir(&fixture(), &data_dir);
    write_tiny_checkpoint_with_width(&ck, "", D_VL, &python).unwrap();
    let cfg = embodiment();
    std::fs::write(&emb, cfg.to_toml().unwrap()).unwrap();

    let args = |out: &Path, extra: &[&str]| -> Vec<std::ffi::OsString> {
        let mut v: Vec<std::ffi::OsString> = vec![
            "gr00t".into(),
            "features".into(),
            "--checkpoint".into(),
            ck.clone().into(),
            "--data".into(),
            data_dir.clone().into(),
            "--embodiment".into(),
            emb.clone().into(),
            "--out".into(),
            out.into(),
        ];
        v.extend(extra.iter().map(Into::into));
        v
    };
    let run = |a: Vec<OsString>| pir2(&a);
    let o = run(args(&feats, &[]));
    let t = text(&o);
    println!("{t}");
    assert!(o.status.success(), "{t}");
    assert!(
        t.contains("features: 12/12 frames") && t.contains("[12, 8, 20]"),
        "{t}"
    );
    assert!(!partial_path(&feats).exists() && !progress_path(&feats).exists());

    // What `pir2 gr00t train` reads.
    let pf = PrecomputedFeatures::open(&feats).unwrap();
    assert_eq!((pf.frames(), pf.tokens(), pf.dim()), (12, 8, D_VL));
    let rows = embedding_rows(&feats, 12, 8 * D_VL);
    let tensors = candle_core::safetensors::load(&feats, &candle_core::Device::Cpu).unwrap();
    let image: Vec<Vec<u8>> = tensors["image_mask"]
        .to_dtype(candle_core::DType::U8)
        .unwrap()
        .to_vec2()
        .unwrap();
    let attn: Vec<Vec<u8>> = tensors["attention_mask"]
        .to_dtype(candle_core::DType::U8)
        .unwrap()
        .to_vec2()
        .unwrap();

    // The same backbone run directly on the same decoded frames, with each episode's task.
    let files = CheckpointFiles::in_dir(&ck);
    let tok = load_tokenizer(&files, &cfg.prompt).unwrap();
    let data = VideoDataset::open(&data_dir).unwrap();
    let load = |prompt: &str| backbone(&files, &cfg, tok.as_ref(), prompt);
    let mut readers: Vec<FrameReader> = VIEWS
        .iter()
        .map(|_| FrameReader::new(ffmpeg_program(), DEFAULT_TOLERANCE_S))
        .collect();
    let mut frames = Vec::new();
    let mut g = 0;
    for ep in &data.episodes {
        let mut bb = load(data.task(ep, 0));
        for t in 0..ep.len() {
            let views: Vec<(Vec<u8>, (usize, usize))> = readers
                .iter_mut()
                .zip(VIEWS)
                .map(|(r, k)| {
                    let f = r.frame(&data, k, ep, t).unwrap();
                    (f.rgb.clone(), f.hw)
                })
                .collect();
            let refs: Vec<(&[u8], (usize, usize))> =
                views.iter().map(|(v, hw)| (v.as_slice(), *hw)).collect();
            let want = bb.backbone_embeddings(&refs).unwrap().to_vec();
            assert!(
                want.iter()
                    .zip(&rows[g])
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "row {g} (episode {}, frame {t}) differs from the backbone",
                ep.episode_index
            );
            let lay = bb.layout();
            assert_eq!(
                image[g],
                lay.image_mask
                    .iter()
                    .map(|&b| u8::from(b))
                    .collect::<Vec<_>>()
            );
            assert_eq!(
                attn[g],
                lay.attention_mask
                    .iter()
                    .map(|&b| u8::from(b))
                    .collect::<Vec<_>>()
            );
            frames.push(views);
            g += 1;
        }
    }
    assert_eq!(g, 12);
    // The two tasks give different prompts: the text tokens differ between the episodes.
    assert_ne!(rows[0][4 * D_VL..], rows[5][4 * D_VL..]);

    // Deployment agrees: `pir2 gr00t run`'s path (`encode_views`: vlln, here the identity
    // LayerNorm, and no VL self-attention in this copy) on frame 7 is LayerNorm(row 7).
    std::fs::remove_file(&files.vl_self_attention).unwrap();
    let mut deploy = load(data.task(&data.episodes[1], 0));
    let views: Vec<pir2_runtime::View> = frames[7]
        .iter()
        .map(|(v, hw)| pir2_runtime::View {
            image: v.clone(),
            hw: *hw,
        })
        .collect();
    let deployed = deploy.encode_views(&views).unwrap().to_vec();
    for (tok_i, (a, b)) in deployed.chunks(D_VL).zip(rows[7].chunks(D_VL)).enumerate() {
        let ln = layer_norm(b);
        let err = a
            .iter()
            .zip(&ln)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max);
        assert!(err < 1e-5, "token {tok_i}: deployment vs features {err}");
    }

    // Bad inputs: one error each, naming what is wrong, and no output.
    let bad = root.join("bad.safetensors");
    let bad_emb = root.join("bad.toml");
    let mut no_cams = cfg.clone();
    no_cams.cameras.clear();
    std::fs::write(&bad_emb, no_cams.to_toml().unwrap()).unwrap();
    let mut a = args(&bad, &[]);
    a[7] = bad_emb.clone().into();
    let o = run(a.clone());
    assert!(
        !o.status.success() && text(&o).contains("`cameras` names no camera view"),
        "{}",
        text(&o)
    );
    let mut top = cfg.clone();
    top.cameras[1] = "observation.images.top".into();
    std::fs::write(&bad_emb, top.to_toml().unwrap()).unwrap();
    let o = run(a);
    let t = text(&o);
    assert!(
        !o.status.success() && t.contains("observation.images.top") && t.contains(VIEWS[1]),
        "{t}"
    );
    let o = {
        let a = args(&bad, &[]);
        Command::new(env!("CARGO_BIN_EXE_pir2"))
            .args(&a)
            .env("PIR2_FFMPEG", root.join("no-such-ffmpeg"))
            .output()
            .unwrap()
    };
    let t = text(&o);
    println!("{t}");
    assert!(
        !o.status.success() && t.contains("no-such-ffmpeg") && t.contains("FFmpeg"),
        "{t}"
    );
    assert!(!bad.exists() && !partial_path(&bad).exists());

    // An existing output is not replaced without --overwrite; with it, the same bytes.
    let o = run(args(&feats, &[]));
    assert!(
        !o.status.success() && text(&o).contains("--overwrite"),
        "{}",
        text(&o)
    );
    let first = std::fs::read(&feats).unwrap();
    let o = run(args(&feats, &["--overwrite"]));
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        std::fs::read(&feats).unwrap() == first,
        "a second run differs"
    );

    // Interrupted after 5 frames (mid episode 0/1 boundary), refused without --resume,
    // resumed to the same bytes.
    let part = root.join("part.safetensors");
    let mut lo = Gr00tFeaturesOptions::new(&ck, &data_dir, &part);
    lo.embodiment = Some(emb.clone());
    lo.stop_after = Some(6);
    let s = extract(&lo, |_| {}).unwrap();
    assert!(s.interrupted() && s.done == 6, "{s:?}");
    assert!(partial_path(&part).exists() && !part.exists());
    let o = run(args(&part, &[]));
    assert!(
        !o.status.success() && text(&o).contains("--resume"),
        "{}",
        text(&o)
    );
    let o = run(args(&part, &["--resume"]));
    let t = text(&o);
    assert!(
        o.status.success() && t.contains("resumed at frame 6"),
        "{t}"
    );
    assert!(
        std::fs::read(&part).unwrap() == first,
        "the resumed file differs"
    );

    // `pir2 gr00t train --features` takes the file (the `alt` head has D_vl = 20).
    let head = root.join("head");
    alt_checkpoint(&head);
    let out = root.join("run");
    let mut a = train_args(&head, &data_dir, &emb, &feats, &out);
    a.extend(["--steps", "2", "--batch-size", "4"].map(OsString::from));
    let o = run(a);
    let t = text(&o);
    println!("{t}");
    assert!(o.status.success(), "{t}");
    assert!(out.join("step-000002/model.safetensors").exists(), "{t}");
}

/// GR00T's split export (ViT + LLM glued in Rust) with the BPE tokenizer and the chat
/// template, the embodiment taken from the checkpoint (no `--embodiment`): every row equals
/// the split backbone run directly on the decoded frames with the episode's task (the prompt
/// changes between the episodes: the token-table rows and positions are re-read).
#[test]
fn split_backbone_features_equal_the_split_backbone_on_the_frames() {
    let dir = Scratch::new("gr00t-features-split");
    let root = dir.path();
    let python = python_from_env().unwrap();
    let ck = root.join("ck");
    write_tiny_checkpoint(&ck, "", &python).unwrap();
    add_bpe_tokenizer(&ck).unwrap();
    let path = ck.join("embodiment.toml");
    let mut cfg = EmbodimentConfig::load(&path).unwrap();
    cfg.prompt.chat.images = 2;
    cfg.prompt.image_tokens = 8;
    cfg.vision.patch_size = 4;
    cfg.vision.temporal_patch_size = 2;
    cfg.vision.merge_size = 2;
    cfg.cameras = VIEWS.map(String::from).to_vec();
    std::fs::write(&path, cfg.to_toml().unwrap()).unwrap();
    write_split_backbone(&ck, "pick the cube", "", &python).unwrap();
    let data_dir = root.join("data");
    copy_dir(&fixture(), &data_dir);
    let out = root.join("split.safetensors");
    let s = extract(&Gr00tFeaturesOptions::new(&ck, &data_dir, &out), |_| {}).unwrap();
    assert!(s.complete && s.backbone.contains("split export"), "{s:?}");
    let (n, t, d) = s.shape;
    assert_eq!(n, 12);
    let rows = embedding_rows(&out, n, t * d);
    let files = CheckpointFiles::in_dir(&ck);
    let tok = load_tokenizer(&files, &cfg.prompt).unwrap();
    let data = VideoDataset::open(&data_dir).unwrap();
    let mut readers: Vec<FrameReader> = VIEWS
        .iter()
        .map(|_| FrameReader::new(ffmpeg_program(), DEFAULT_TOLERANCE_S))
        .collect();
    let mut g = 0;
    for ep in &data.episodes {
        let mut bb = backbone(&files, &cfg, tok.as_ref(), data.task(ep, 0));
        assert!(bb.is_split());
        for f in 0..ep.len() {
            let views: Vec<(Vec<u8>, (usize, usize))> = readers
                .iter_mut()
                .zip(VIEWS)
                .map(|(r, k)| {
                    let fr = r.frame(&data, k, ep, f).unwrap();
                    (fr.rgb.clone(), fr.hw)
                })
                .collect();
            let refs: Vec<(&[u8], (usize, usize))> =
                views.iter().map(|(v, hw)| (v.as_slice(), *hw)).collect();
            let want = bb.backbone_embeddings(&refs).unwrap();
            assert!(
                want.iter()
                    .zip(&rows[g])
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "row {g} (episode {}, frame {f}) differs from the split backbone",
                ep.episode_index
            );
            g += 1;
        }
    }
    assert_eq!(g, n);
}

/// The image-typed camera of the image test.
const SIDE: &str = "observation.images.side";

/// Adds an image feature to a copy of the video fixture the way LeRobot v3.0 stores one (a
/// column of the data file holding, per frame, Hugging Face `datasets`' `Image` struct
/// `{bytes, path}`; `"dtype": "image"` in `meta/info.json`): episode 0 as PNG (LeRobot's
/// image writer), episode 1 as JPEG, 28×20 px. Writes Pillow's decoding of every frame
/// (`Image.open(...).convert("RGB")`, what LeRobot's loader gets for these RGB images) to
/// `argv[3]`. `argv[4]` = `EP:FRAME` truncates that frame's PNG/JPEG bytes to half.
const IMAGE_DATASET: &str = r#"
import io, json, sys
import numpy as np
import pyarrow as pa, pyarrow.parquet as pq
from PIL import Image

root, key, raw = sys.argv[1], sys.argv[2], sys.argv[3]
corrupt = tuple(int(x) for x in sys.argv[4].split(":")) if len(sys.argv) > 4 else None
W, H = 28, 20
path = f"{root}/data/chunk-000/file-000.parquet"
t = pq.read_table(path)
eps, frames = t["episode_index"].to_pylist(), t["frame_index"].to_pylist()
cells, out = [], open(raw, "wb")
for i, (ep, fr) in enumerate(zip(eps, frames)):
    y, x = np.mgrid[0:H, 0:W]
    k = 31 * ep + 11 * fr
    img = np.stack([(x * 9 + k) % 256, (y * 12 + 3 * k) % 256, ((x * y) + k) % 256], -1)
    img = img.astype(np.uint8)
    img[(fr * 2) % (H - 5):(fr * 2) % (H - 5) + 5, 3:9] = [250, 250, 10]
    buf = io.BytesIO()
    if ep == 0:
        Image.fromarray(img).save(buf, format="PNG"); name = f"frame-{i:06d}.png"
    else:
        Image.fromarray(img).save(buf, format="JPEG", quality=90); name = f"frame-{i:06d}.jpg"
    b = buf.getvalue()
    out.write(np.asarray(Image.open(io.BytesIO(b)).convert("RGB")).tobytes())
    if corrupt == (ep, fr):
        b = b[: len(b) // 2]
    cells.append({"bytes": b, "path": name})
out.close()
image_type = pa.struct([("bytes", pa.binary()), ("path", pa.string())])
t = t.append_column(key, pa.array(cells, type=image_type))
pq.write_table(t, path)
info_path = f"{root}/meta/info.json"
info = json.load(open(info_path))
info["features"][key] = {"dtype": "image", "shape": [H, W, 3], "names": ["height", "width", "channels"]}
json.dump(info, open(info_path, "w"), indent=4)
"#;

fn image_dataset(python: &Path, root: &Path, data: &Path, raw: &Path, corrupt: Option<&str>) {
    copy_dir(&fixture(), data);
    let mut args = vec![data.as_os_str(), SIDE.as_ref(), raw.as_os_str()];
    args.extend(corrupt.map(std::ffi::OsStr::new));
    run_python(
        python,
        &root.join("image_dataset.py"),
        IMAGE_DATASET,
        &args,
        "image dataset",
    );
}

/// An image-typed camera (PNG/JPEG bytes in the data file, LeRobot v3.0's `image` feature)
/// next to a video camera: pir2's pixels equal Pillow's decoding of the same bytes (PNG
/// exactly; JPEG within the decoders' rounding), every features row equals, bit for bit, the
/// backbone run directly on those frames (for the PNG episode: on Pillow's pixels), a
/// corrupt image is one error naming the data file, the camera, the episode and the frame,
/// and a depth video is refused by name.
#[test]
fn image_camera_features_are_the_backbone_on_pillows_pixels() {
    let dir = Scratch::new("gr00t-features-image");
    let root = dir.path();
    let python = python_from_env().unwrap();
    let (data_dir, raw) = (root.join("data"), root.join("pillow.raw"));
    image_dataset(&python, root, &data_dir, &raw, None);
    let data = VideoDataset::open(&data_dir).unwrap();
    assert_eq!(data.image_keys, [SIDE]);
    assert_eq!(data.video_keys, VIEWS);
    let cams = vec![VIEWS[0].to_string(), SIDE.to_string()];
    data.check_views(&cams).unwrap();
    // The state-only reader (`pir2 gr00t train`) still reads the dataset.
    assert_eq!(
        pir2_sim::dataset::read_selected(&data_dir, &state_and_action())
            .unwrap()
            .total_frames(),
        12
    );

    // Pixels: pir2 against Pillow, every frame.
    let pillow = std::fs::read(&raw).unwrap();
    let n = 20 * 28 * 3;
    assert_eq!(pillow.len(), 12 * n);
    let mut reader = FrameReader::new(ffmpeg_program(), DEFAULT_TOLERANCE_S);
    let (mut g, mut png_max, mut jpeg_max, mut jpeg_sum, mut jpeg_n) = (0, 0u8, 0u8, 0u64, 0);
    for ep in &data.episodes {
        for t in 0..ep.len() {
            let f = reader.frame(&data, SIDE, ep, t).unwrap();
            assert_eq!(f.hw, (20, 28));
            assert_eq!(f.time, ep.timestamps[t]);
            let d = f
                .rgb
                .iter()
                .zip(&pillow[g * n..(g + 1) * n])
                .map(|(a, b)| a.abs_diff(*b))
                .max()
                .unwrap();
            if ep.episode_index == 0 {
                png_max = png_max.max(d);
            } else {
                jpeg_max = jpeg_max.max(d);
                jpeg_sum += f
                    .rgb
                    .iter()
                    .zip(&pillow[g * n..(g + 1) * n])
                    .map(|(a, b)| u64::from(a.abs_diff(*b)))
                    .sum::<u64>();
                jpeg_n += n;
            }
            g += 1;
        }
    }
    let jpeg_mean = jpeg_sum as f64 / jpeg_n as f64;
    println!(
        "pir2 vs Pillow: PNG max |diff| {png_max}; JPEG max |diff| {jpeg_max}, mean {jpeg_mean:.3}"
    );
    assert_eq!(png_max, 0, "PNG pixels differ from Pillow's");
    // JPEG decoders are not bit-identical (the standard leaves IDCT rounding and chroma
    // upsampling open): the `image` crate's and Pillow's libjpeg-turbo differ by a few levels.
    assert!(
        jpeg_max <= 4 && jpeg_mean < 0.5,
        "JPEG pixels differ from Pillow's by up to {jpeg_max} (mean {jpeg_mean})"
    );

    // Features: a video camera and the image camera, through the library `extract`.
    let ck = root.join("ck");
    write_tiny_checkpoint_with_width(&ck, "", D_VL, &python).unwrap();
    let mut cfg = embodiment();
    cfg.cameras = cams.clone();
    let emb = root.join("embodiment.toml");
    std::fs::write(&emb, cfg.to_toml().unwrap()).unwrap();
    let feats = root.join("features.safetensors");
    let mut o = Gr00tFeaturesOptions::new(&ck, &data_dir, &feats);
    o.embodiment = Some(emb.clone());
    let s = extract(&o, |_| {}).unwrap();
    assert!(s.complete && s.shape == (12, 8, D_VL), "{s:?}");
    let rows = embedding_rows(&feats, 12, 8 * D_VL);
    let files = CheckpointFiles::in_dir(&ck);
    let tok = load_tokenizer(&files, &cfg.prompt).unwrap();
    let mut video = FrameReader::new(ffmpeg_program(), DEFAULT_TOLERANCE_S);
    let mut image = FrameReader::new(ffmpeg_program(), DEFAULT_TOLERANCE_S);
    let mut g = 0;
    for ep in &data.episodes {
        let mut bb = backbone(&files, &cfg, tok.as_ref(), data.task(ep, 0));
        for t in 0..ep.len() {
            let front = video.frame(&data, VIEWS[0], ep, t).unwrap();
            let side = image.frame(&data, SIDE, ep, t).unwrap();
            if ep.episode_index == 0 {
                // PNG: Pillow's pixels exactly (checked above), so this is the backbone on them.
                assert_eq!(side.rgb, pillow[g * n..(g + 1) * n]);
            }
            let views = [
                (front.rgb.as_slice(), front.hw),
                (side.rgb.as_slice(), side.hw),
            ];
            let want = bb.backbone_embeddings(&views).unwrap().to_vec();
            assert!(
                want.iter()
                    .zip(&rows[g])
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "row {g} (episode {}, frame {t}) differs from the backbone on the frames",
                ep.episode_index
            );
            g += 1;
        }
    }
    // The image camera matters: another frame there gives another row.
    assert_ne!(rows[0], rows[1]);

    // A corrupt image: one error naming the data file, the camera, the episode and the frame.
    let bad_dir = root.join("bad");
    image_dataset(&python, root, &bad_dir, &root.join("bad.raw"), Some("0:3"));
    let bad = root.join("bad.safetensors");
    let mut o = Gr00tFeaturesOptions::new(&ck, &bad_dir, &bad);
    o.embodiment = Some(emb.clone());
    let e = format!("{:#}", extract(&o, |_| {}).unwrap_err());
    println!("{e}");
    assert!(
        e.contains("file-000.parquet")
            && e.contains(SIDE)
            && e.contains("episode 0, frame 3")
            && e.contains("does not decode"),
        "{e}"
    );
    assert!(!bad.exists());

    // A depth video (LeRobot's `video.is_depth_map`) is refused by name.
    let info_path = data_dir.join("meta/info.json");
    let mut info = read_json(&info_path);
    info["features"][VIEWS[0]]["info"]["video.is_depth_map"] = true.into();
    std::fs::write(&info_path, info.to_string()).unwrap();
    let data = VideoDataset::open(&data_dir).unwrap();
    let e = data.check_views(&cams).unwrap_err().to_string();
    println!("{e}");
    assert!(e.contains(VIEWS[0]) && e.contains("depth"), "{e}");
}
