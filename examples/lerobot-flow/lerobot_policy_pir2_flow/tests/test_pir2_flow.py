"""Tests of the pir2_flow LeRobot policy plugin (need torch, lerobot 0.4.4, onnxruntime, pir2).

A small LeRobotDataset is written here with LeRobot's own writer (3 episodes of seeded random
walks with the ball-on-plate feature layout), so no pir2 binary is needed.
"""

import copy
import hashlib
import json

import draccus
import numpy as np
import pir2
import pytest
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import NormalizationMode
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import (
    get_policy_class,
    make_policy,
    make_policy_config,
    make_pre_post_processors,
)
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_policy_pir2_flow import Pir2FlowConfig, Pir2FlowPolicy
from lerobot_policy_pir2_flow.export import export
from lerobot_policy_pir2_flow.flow import compute_stats, flow_loss, load_episodes
from lerobot_policy_pir2_flow.modeling_pir2_flow import SAMPLE_STREAM

FPS, F, S, A = 50, 6, 4, 2
EPISODE_LENGTHS = (30, 7, 22)  # one shorter than the window + horizon


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds") / "ballplate"
    features = {
        OBS_STATE: {"dtype": "float32", "shape": (F,), "names": None},
        OBS_ENV_STATE: {"dtype": "float32", "shape": (S,), "names": None},
        ACTION: {"dtype": "float32", "shape": (A,), "names": None},
    }
    ds = LeRobotDataset.create("local/ballplate", FPS, features, root=root, use_videos=False)
    rng = np.random.default_rng(7)
    for n in EPISODE_LENGTHS:
        state = np.cumsum(rng.normal(size=(n, F)), 0).astype(np.float32)
        env = np.cumsum(rng.normal(size=(n, S)), 0).astype(np.float32)
        act = rng.normal(scale=0.1, size=(n, A)).astype(np.float32)
        for t in range(n):
            ds.add_frame({OBS_STATE: state[t], OBS_ENV_STATE: env[t], ACTION: act[t], "task": "hold"})
        ds.save_episode()
    ds.finalize()
    return root


def make(dataset_root, **overrides):
    """(config, dataset with the config's delta_timestamps, policy, pre, post) as lerobot-train
    builds them."""
    cfg = make_policy_config("pir2_flow", device="cpu", width=32, depth=2, **overrides)
    meta = LeRobotDataset("local/ballplate", root=dataset_root).meta
    ds = LeRobotDataset("local/ballplate", root=dataset_root,
                        delta_timestamps=resolve_delta_timestamps(cfg, meta))
    torch.manual_seed(0)
    policy = make_policy(cfg, ds_meta=ds.meta)
    pre, post = make_pre_post_processors(cfg, dataset_stats=ds.meta.stats)
    return cfg, ds, policy, pre, post


def batch_of(ds, pre, indices):
    items = [ds[i] for i in indices]
    batch = torch.utils.data.default_collate(items)
    return pre(batch)


# Frames: episode starts (history and slow age clamped), an episode end (actions repeated), middle.
INDICES = [0, 1, 2, 29, 30, 31, 36, 37, 40, 58]


def test_registered_under_pir2_flow():
    assert PreTrainedConfig.get_choice_class("pir2_flow") is Pir2FlowConfig
    assert get_policy_class("pir2_flow") is Pir2FlowPolicy
    cfg = make_policy_config("pir2_flow", device="cpu")
    assert isinstance(cfg, Pir2FlowConfig) and cfg.type == "pir2_flow"
    assert (cfg.horizon, cfg.n_obs_steps, cfg.d_vis_max, cfg.policy) == (16, 2, 3, "pi_r2")
    assert cfg.observation_delta_indices == [-3, -2, -1, 0]
    assert cfg.action_delta_indices == list(range(16))


def test_make_policy_from_dataset_features(dataset_root):
    cfg, ds, policy, pre, post = make(dataset_root)
    assert isinstance(policy, Pir2FlowPolicy)
    assert set(cfg.input_features) == {OBS_STATE, OBS_ENV_STATE}
    assert set(cfg.output_features) == {ACTION}
    assert (cfg.fast_dim, cfg.slow_dim, cfg.action_dim) == (F, S, A)
    _, episodes = load_episodes(dataset_root, [OBS_STATE], [OBS_ENV_STATE], ACTION)
    want = compute_stats(episodes)
    got = policy.model.stats()
    for key in ("fast", "fast_diff", "slow"):
        assert got[key] == want[key], key
    # The preprocessor passes observations raw and normalises the actions (LeRobot's MEAN_STD).
    b = batch_of(ds, pre, [5])
    raw = ds[5]
    assert torch.equal(b[OBS_STATE][0], raw[OBS_STATE])
    st = ds.meta.stats[ACTION]
    mean, std = torch.tensor(st["mean"]).float(), torch.tensor(st["std"]).float()
    torch.testing.assert_close(b[ACTION][0], (raw[ACTION] - mean) / (std + 1e-8))


def test_forward_is_pir2_loss_on_pir2_windows(dataset_root):
    cfg, ds, policy, pre, _ = make(dataset_root)
    batch = batch_of(ds, pre, INDICES)
    draw_rng = pir2.Rng.from_state(pir2.Rng(cfg.seed).state)
    sample_rng = pir2.Rng.derive(cfg.seed, SAMPLE_STREAM)
    loss, info = policy.forward(batch)
    assert torch.isfinite(loss) and loss.item() > 0 and "mean_delay" in info

    # The same samples cut as train.py's Sampler cuts them from the episodes (history and
    # slow age clamped at the episode start, the last action repeated past the end), with
    # the same generators: the ages then ε from Rng.derive(seed, 1), the draws from Rng(seed).
    _, episodes = load_episodes(dataset_root, [OBS_STATE], [OBS_ENV_STATE], ACTION)
    starts = np.cumsum([0, *EPISODE_LENGTHS])
    st = ds.meta.stats[ACTION]
    a_mean, a_std = np.float32(st["mean"]), np.float32(st["std"]) + np.float32(1e-8)
    b, h = len(INDICES), cfg.horizon
    d_vis = np.array([sample_rng.below(cfg.d_vis_max + 1) for _ in range(b)], np.int64)
    eps = sample_rng.normal(b * h * A).reshape(b, h, A)
    draws = cfg.train_schedule().draw(b, h, draw_rng)
    fast, slow, act = [], [], []
    for i, k in enumerate(INDICES):
        e = int(np.searchsorted(starts, k, side="right")) - 1
        t = k - starts[e]
        f, s, a = episodes[e]
        fast.append(f[[max(t + j + 1 - cfg.n_obs_steps, 0) for j in range(cfg.n_obs_steps)]])
        slow.append(s[max(t - d_vis[i], 0)])
        act.append((a[[min(t + p, len(a) - 1) for p in range(h)]] - a_mean) / a_std)
    want = flow_loss(policy.model, draws, np.stack(act).astype(np.float32), eps,
                     np.stack(fast), np.stack(slow), d_vis)
    assert abs(loss.item() - want.item()) <= 1e-6, (loss.item(), want.item())

    # The generators advanced and are buffers: the next call draws anew.
    assert policy.draw_rng_state.tolist() != torch.from_numpy(
        np.asarray(pir2.Rng(cfg.seed).state, np.uint64).view(np.int64)).tolist()
    loss2, _ = policy.forward(batch)
    assert loss2.item() != loss.item()


def test_export_matches_onnx_runtime(dataset_root, tmp_path):
    import onnxruntime as ort

    cfg, ds, policy, pre, post = make(dataset_root)
    # A few steps so the weights are not the initial ones.
    opt = torch.optim.AdamW(policy.get_optim_params(), lr=1e-3)
    for _ in range(3):
        loss, _ = policy.forward(batch_of(ds, pre, INDICES))
        opt.zero_grad()
        loss.backward()
        opt.step()
    saved = tmp_path / "pretrained_model"
    policy.save_pretrained(saved)
    pre.save_pretrained(saved)
    post.save_pretrained(saved)
    out = tmp_path / "onnx"
    err, name = export(saved, out)
    assert name == "pi_r2" and err < 1e-5
    assert sorted(p.name for p in out.iterdir()) == ["identity.json", "model.onnx", "stats.json"]
    identity = json.loads((out / "identity.json").read_text())
    assert identity == {"policy": "pi_r2",
                        "weights_sha256": hashlib.sha256((out / "model.onnx").read_bytes()).hexdigest()}
    stats = json.loads((out / "stats.json").read_text())
    st = ds.meta.stats[ACTION]
    assert stats["action"]["mean"] == torch.tensor(st["mean"]).float().tolist()
    assert stats["action"]["std"] == torch.tensor(st["std"]).float().tolist()
    assert {k: stats[k] for k in ("fast", "fast_diff", "slow")} == policy.model.stats()

    # ONNX Runtime on the exported graph = the torch policy's velocity, on a real batch.
    batch = batch_of(ds, pre, INDICES)
    g = torch.Generator().manual_seed(3)
    b = len(INDICES)
    x = torch.randn(b, cfg.horizon, A, generator=g)
    tau = torch.rand(b, cfg.horizon, generator=g)
    tau[:3, :2] = pir2.HIDDEN_FRONT_TAU
    fast = batch[OBS_STATE][:, -cfg.n_obs_steps:]
    slow = batch[OBS_ENV_STATE][:, -1]
    d_vis = torch.randint(0, cfg.d_vis_max + 1, (b,), generator=g)
    sess = ort.InferenceSession(str(out / "model.onnx"), providers=["CPUExecutionProvider"])
    names = ["x", "tau", "obs_fast", "obs_slow", "d_vis"]
    got = sess.run(["v"], dict(zip(names, (t.numpy() for t in (x, tau, fast, slow, d_vis)))))[0]
    with torch.no_grad():
        want = policy.model(x, tau, fast, slow, d_vis).numpy()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)

    with pytest.raises(FileExistsError, match="already exists"):
        export(saved, out)


def test_command_line_fields_parse_as_lerobot_train_parses_them():
    cfg = draccus.parse(Pir2FlowConfig, args=[
        "--device=cpu", '--recipe={"nfe": 3, "jitter": 0.1}', "--policy=pi_r2_hidden",
        "--fast_features=[observation.state]", "--slow_features=[]", "--d_vis_max=5"])
    assert cfg.recipe == {"nfe": 3, "jitter": 0.1} and cfg.policy == "pi_r2_hidden"
    assert cfg.slow_features == [] and cfg.observation_delta_indices == [-1, 0]
    with pytest.raises(Exception) as e:
        draccus.parse(Pir2FlowConfig, args=["--device=cpu", '--recipe={"nfes": 3}'])
    msg = str(e.value.__cause__ or e.value)
    assert 'unknown field "nfes"' in msg, msg


def test_save_pretrained_round_trip_is_bit_exact(dataset_root, tmp_path):
    cfg, ds, policy, pre, _ = make(dataset_root, recipe={"nfe": 3}, policy="pi_r2_hidden")
    batch = batch_of(ds, pre, INDICES)
    policy.forward(batch)  # advance the generators: their state must be saved too
    policy.save_pretrained(tmp_path / "p")
    loaded = Pir2FlowPolicy.from_pretrained(tmp_path / "p")
    a, b = policy.state_dict(), loaded.state_dict()
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), k
    assert loaded.config.policy == cfg.policy and loaded.config.recipe == cfg.recipe
    assert loaded.config.normalization_mapping == cfg.normalization_mapping
    # Resumed: both continue the same draw sequence.
    la, _ = policy.forward(batch)
    lb, _ = loaded.forward(batch)
    assert la.item() == lb.item()


def test_select_action_is_seeded_and_shaped(dataset_root):
    cfg, ds, policy, pre, post = make(dataset_root, n_action_steps=4)
    policy.eval()
    frame = {k: v[:, -1] for k, v in batch_of(ds, pre, [0, 40]).items()
             if k in (OBS_STATE, OBS_ENV_STATE)}
    first = [post(policy.select_action(dict(frame))) for _ in range(5)]
    assert first[0].shape == (2, A)
    policy.reset()
    again = [post(policy.select_action(dict(frame))) for _ in range(5)]
    for x, y in zip(first, again):
        assert torch.equal(x, y)
    chunk = policy.predict_action_chunk(frame)
    assert chunk.shape == (2, cfg.horizon, A) and torch.isfinite(chunk).all()


def test_bad_input_is_named(dataset_root):
    cfg, ds, policy, pre, _ = make(dataset_root)
    batch = batch_of(ds, pre, INDICES[:2])
    missing = {k: v for k, v in batch.items() if k != OBS_ENV_STATE}
    with pytest.raises(ValueError, match="observation.environment_state"):
        policy.forward(missing)
    short = dict(batch, **{OBS_STATE: batch[OBS_STATE][:, -1:]})
    with pytest.raises(ValueError, match=r"observation\.state.*expected a window"):
        policy.forward(short)
    nan = dict(batch, **{OBS_STATE: batch[OBS_STATE].clone()})
    nan[OBS_STATE][0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"observation\.state.*NaN"):
        policy.forward(nan)
    bad_act = dict(batch, **{ACTION: batch[ACTION][:, :3]})
    with pytest.raises(ValueError, match="action.*expected"):
        policy.forward(bad_act)

    with pytest.raises(ValueError, match="must be IDENTITY"):
        Pir2FlowConfig(device="cpu", normalization_mapping={
            "STATE": NormalizationMode.MEAN_STD, "ENV": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.MEAN_STD})
    with pytest.raises(ValueError, match="unknown policy 'pir3'"):
        Pir2FlowConfig(device="cpu", policy="pir3")
    with pytest.raises(ValueError, match="recipe must be a mapping"):
        Pir2FlowConfig(device="cpu", recipe="paper_sim")
    with pytest.raises(ValueError, match=r'unknown field "nfes"; the fields are .*nfe'):
        Pir2FlowConfig(device="cpu", recipe={"nfes": 2})
    with pytest.raises(ValueError, match="recipe"):
        Pir2FlowConfig(device="cpu", recipe={"nfe": "two"})
    assert Pir2FlowConfig(device="cpu", recipe={"nfe": 3}).train_schedule() == \
        pir2.TrainSchedule.for_policy("pi_r2", {"nfe": 3})
    wrong = copy.deepcopy(cfg)
    wrong.fast_features = ["observation.joints"]
    with pytest.raises(ValueError, match="fast feature 'observation.joints'"):
        Pir2FlowPolicy(wrong)

    fresh = Pir2FlowPolicy(copy.deepcopy(cfg))  # no dataset, nothing loaded
    with pytest.raises(RuntimeError, match="no observation statistics"):
        fresh.forward(batch)
