"""The πR² flow network, its loss and its ONNX export, shared by the LeRobot policy
(:mod:`lerobot_policy_pir2_flow.modeling_pir2_flow`) and ``examples/lerobot-flow/train.py``.

Everything here follows pir2's own trainer where pir2 defines the numbers: the normalisation
statistics (:func:`compute_stats`, the formula and floor of pir2's ``Norm``), the observation
encoding (``o_t`` and its successive differences, each by their own statistics), the masked
flow loss (:func:`flow_loss`) on the draws of ``pir2.TrainSchedule`` and the ONNX contract of
an ONNX checkpoint (:func:`export_checkpoint`).
"""

from __future__ import annotations

import hashlib
import json
import math
import pathlib

import numpy as np
import torch
from torch import nn

#: Names of the graph's inputs, in the order :meth:`FlowMLP.forward` takes them.
ONNX_INPUTS = ("x", "tau", "obs_fast", "obs_slow", "d_vis")
#: Files of an ONNX checkpoint.
ONNX_FILE, STATS_FILE, IDENTITY_FILE = "model.onnx", "stats.json", "identity.json"


def load_episodes(root, fast_keys, slow_keys, action_key, repo_id=None):
    """Per-episode (fast [T,F], slow [T,S], action [T,A]) float32 arrays, read with LeRobot's
    ``LeRobotDataset`` from the dataset at ``root``; returns ``(dataset, episodes)``."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    repo_id = repo_id or "local/" + pathlib.Path(root).name
    ds = LeRobotDataset(repo_id=repo_id, root=root)
    missing = [k for k in (*fast_keys, *slow_keys, action_key) if k not in ds.features]
    if missing:
        raise ValueError(f"{root}: the dataset has no feature {', '.join(missing)} "
                         f"(it has {', '.join(sorted(ds.features))})")
    cols = ["episode_index", "frame_index", *fast_keys, *slow_keys, action_key]
    table = ds.hf_dataset.select_columns(cols).with_format("numpy")[:]
    ep, frame = table["episode_index"], table["frame_index"]

    def cat(keys):
        if not keys:
            return np.zeros((len(ep), 0), np.float32)
        return np.concatenate(
            [np.asarray(table[k], np.float32).reshape(len(ep), -1) for k in keys], axis=1
        )

    fast, slow, action = cat(fast_keys), cat(slow_keys), cat([action_key])
    for name, arr in (("fast", fast), ("slow", slow), ("action", action)):
        if not np.isfinite(arr).all():
            raise ValueError(f"{root}: the {name} features hold NaN or infinite values")
    episodes = []
    for e in np.unique(ep):  # episodes in episode_index order, frames in frame order
        rows = np.flatnonzero(ep == e)
        rows = rows[np.argsort(frame[rows], kind="stable")]
        episodes.append((fast[rows], slow[rows], action[rows]))
    return ds, episodes


def norm(rows):
    """pir2's Norm: mean and population std (f64 sums), std floored at 1e-4."""
    rows = np.asarray(rows, np.float64)
    n = max(len(rows), 1)
    mean = rows.sum(0) / n
    var = np.maximum((rows * rows).sum(0) / n - mean * mean, 0.0)
    std = np.maximum(np.sqrt(var).astype(np.float32), np.float32(1e-4))
    return {"mean": mean.astype(np.float32).tolist(), "std": std.tolist()}


def compute_stats(episodes):
    """pir2's stats.json: fast obs, successive fast differences within episodes, slow, action."""
    fast = np.concatenate([f for f, _, _ in episodes])
    diff = np.concatenate([f[1:] - f[:-1] for f, _, _ in episodes])
    slow = np.concatenate([s for _, s, _ in episodes])
    action = np.concatenate([a for _, _, a in episodes])
    return {"fast": norm(fast), "fast_diff": norm(diff), "slow": norm(slow), "action": norm(action)}


class FlowMLP(nn.Module):
    """A velocity MLP with pir2's observation normalisation inside (the graph takes raw obs).

    Input: the noisy chunk, per-position τ features (τ, sin πkτ, cos πkτ; a hidden front's
    τ = -1 passes through the same features), the fast history encoded as pir2 encodes it
    ([norm(o_t), norm_d(o_t - o_{t-1}), ...]), the normalised slow features and a one-hot of
    the clamped slow-feature age d_vis. Output: the velocity in normalised action units.

    ``stats`` holds the ``fast``, ``fast_diff`` and ``slow`` statistics (:func:`compute_stats`);
    ``None`` leaves them NaN, to be loaded from a saved state (:meth:`has_stats` says which).
    """

    def __init__(self, stats, horizon, action_dim, n_obs, fast_dim, slow_dim, d_vis_max,
                 width, depth, tau_freqs):
        super().__init__()
        self.h, self.a, self.n_obs, self.d_vis_max = horizon, action_dim, n_obs, d_vis_max
        self.fast_dim, self.slow_dim = fast_dim, slow_dim

        def t(key, part, dim):
            if stats is None:
                return torch.full((dim,), float("nan"))
            v = torch.tensor(stats[key][part], dtype=torch.float32)
            if v.shape != (dim,):
                raise ValueError(f"stats.{key}.{part} has {tuple(v.shape)} values, expected {dim}")
            return v

        self.register_buffer("fast_mean", t("fast", "mean", fast_dim))
        self.register_buffer("fast_std", t("fast", "std", fast_dim))
        self.register_buffer("diff_mean", t("fast_diff", "mean", fast_dim))
        self.register_buffer("diff_std", t("fast_diff", "std", fast_dim))
        self.register_buffer("slow_mean", t("slow", "mean", slow_dim))
        self.register_buffer("slow_std", t("slow", "std", slow_dim))
        self.register_buffer("freqs", math.pi * torch.arange(1, tau_freqs + 1, dtype=torch.float32))
        self.register_buffer("ages", torch.arange(d_vis_max + 1, dtype=torch.int64))
        d_in = horizon * action_dim + horizon * (1 + 2 * tau_freqs) + n_obs * fast_dim
        d_in += slow_dim + d_vis_max + 1
        layers = []
        for _ in range(depth):
            layers += [nn.Linear(d_in, width), nn.SiLU()]
            d_in = width
        layers.append(nn.Linear(d_in, horizon * action_dim))
        self.net = nn.Sequential(*layers)

    def has_stats(self):
        """Whether the normalisation statistics are set (not NaN)."""
        bufs = (self.fast_mean, self.fast_std, self.diff_mean, self.diff_std,
                self.slow_mean, self.slow_std)
        return all(bool(torch.isfinite(b).all()) for b in bufs)

    def stats(self):
        """The ``fast``, ``fast_diff`` and ``slow`` statistics as in pir2's stats.json."""
        def pair(m, s):
            return {"mean": m.detach().cpu().tolist(), "std": s.detach().cpu().tolist()}

        return {"fast": pair(self.fast_mean, self.fast_std),
                "fast_diff": pair(self.diff_mean, self.diff_std),
                "slow": pair(self.slow_mean, self.slow_std)}

    def forward(self, x, tau, obs_fast, obs_slow, d_vis):
        b = x.shape[0]
        ft = tau.unsqueeze(-1) * self.freqs
        tau_feat = torch.cat([tau.unsqueeze(-1), torch.sin(ft), torch.cos(ft)], -1)
        last = obs_fast[:, -1]
        enc = [(last - self.fast_mean) / self.fast_std]
        for k in range(1, self.n_obs):  # k-th difference o_{t-k+1} - o_{t-k}
            d = obs_fast[:, self.n_obs - k] - obs_fast[:, self.n_obs - k - 1]
            enc.append((d - self.diff_mean) / self.diff_std)
        slow = (obs_slow - self.slow_mean) / self.slow_std
        age = torch.clamp(d_vis, 0, self.d_vis_max).unsqueeze(-1)
        one_hot = (age == self.ages).to(x.dtype)
        z = torch.cat(
            [x.reshape(b, -1), tau_feat.reshape(b, -1), *enc, slow, one_hot], -1
        )
        return self.net(z).reshape(b, self.h, self.a)


def flow_loss(model, draws, actions, eps, fast, slow, d_vis):
    """pir2's masked flow loss ``Σ_p mask_p·|v_p − target_p|² / (A·Σ_p mask_p)`` of ``model``.

    ``draws`` is a ``pir2.Draws`` of the batch (``TrainSchedule.draw``); ``actions`` (the
    chunks in normalised units) and ``eps`` (the noise) are float32 arrays ``[B,H,A]``, from
    which ``draws.build`` makes the model input ``x``, its ``τ`` and the target ``a − ε``;
    ``fast [B,n_obs,F]``, ``slow [B,S]`` (raw) and ``d_vis [B]`` are tensors or arrays.
    """
    dev = next(model.parameters()).device
    x, tau_in, target = draws.build(actions, eps)

    def on(a, dtype=torch.float32):
        return torch.as_tensor(a, dtype=dtype).to(dev)

    v = model(on(x), on(tau_in), on(fast), on(slow), on(d_vis, torch.int64))
    mask = on(draws.mask).unsqueeze(-1)
    return (mask * (v - on(target)) ** 2).sum() / (v.shape[-1] * mask.sum())


def cli_policy_name(policy):
    """pir2's ``--policy`` name of a training policy (``pi_r2_hidden`` -> ``pir2-hidden``)."""
    return policy.replace("pi_r2", "pir2").replace("_", "-")


def example_inputs(model, batch=2, seed=0):
    """Inputs of the graph's contract for tracing and checking: seeded, observations around
    the model's own statistics (every hidden-front, visible and slow-age case reachable)."""
    g = torch.Generator().manual_seed(seed)

    def around(mean, std, *shape):
        m = torch.nan_to_num(mean.detach().cpu(), nan=0.0)
        s = torch.nan_to_num(std.detach().cpu(), nan=1.0)
        return m + s * torch.randn(*shape, m.shape[0], generator=g)

    x = torch.randn(batch, model.h, model.a, generator=g)
    tau = torch.rand(batch, model.h, generator=g)
    tau[0, 0] = -1.0  # a hidden front slot
    fast = around(model.fast_mean, model.fast_std, batch, model.n_obs)
    slow = around(model.slow_mean, model.slow_std, batch)
    d_vis = torch.randint(0, model.d_vis_max + 1, (batch,), generator=g)
    return x, tau, fast, slow, d_vis


def export_checkpoint(model, out, policy, stats, example=None, tolerance=1e-4):
    """Write pir2's ONNX checkpoint of ``model`` to the new directory ``out``.

    ``model.onnx`` (dynamic batch, every other size fixed; checked against the torch module
    with ONNX Runtime on ``example`` before anything else is written), ``stats.json``
    (``stats``: ``fast``, ``fast_diff``, ``slow``, ``action`` as pir2 stores them) and
    ``identity.json`` (``policy``, the SHA-256 of ``model.onnx``). Returns the largest
    |ONNX Runtime − torch| difference seen.
    """
    import onnxruntime as ort

    out = pathlib.Path(out)
    if out.exists():
        raise FileExistsError(f"{out} already exists; choose another output directory")
    for key in ("fast", "fast_diff", "slow", "action"):
        for part in ("mean", "std"):
            vals = np.asarray(stats[key][part], np.float64)
            if not np.isfinite(vals).all() or (part == "std" and (vals <= 0).any()):
                raise ValueError(f"stats.{key}.{part} must be finite (and std > 0): {vals.tolist()}")
    model = model.cpu().eval()
    if example is None:
        example = example_inputs(model)
    out.mkdir(parents=True)
    onnx_path = out / ONNX_FILE
    torch.onnx.export(
        model, tuple(example), str(onnx_path), input_names=list(ONNX_INPUTS),
        output_names=["v"], dynamic_axes={n: {0: "batch"} for n in (*ONNX_INPUTS, "v")},
        opset_version=17, dynamo=False,
    )
    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    got = sess.run(["v"], {n: a.numpy() for n, a in zip(ONNX_INPUTS, example)})[0]
    with torch.no_grad():
        want = model(*example).numpy()
    err = float(np.abs(got - want).max())
    if not err < tolerance:
        onnx_path.unlink()
        raise RuntimeError(f"ONNX Runtime and torch differ by {err} (> {tolerance}); "
                           f"{onnx_path} removed")
    (out / STATS_FILE).write_text(json.dumps(stats, indent=2))
    sha = hashlib.sha256(onnx_path.read_bytes()).hexdigest()
    (out / IDENTITY_FILE).write_text(json.dumps({"policy": policy, "weights_sha256": sha}))
    return err
