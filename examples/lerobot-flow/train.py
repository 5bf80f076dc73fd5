"""Train a πR² flow policy in PyTorch on a LeRobotDataset and export it for pir2.

The dataset is read with LeRobot's own ``LeRobotDataset`` (e.g. one ``pir2 collect ballplate``
wrote). Training samples are built as pir2's trainer builds them (pir2-backends/src/train):
a frame ``t`` drawn uniformly over all frames, the fast history ``t-n_obs+1 .. t`` (clamped at
the episode start), the slow features ``d_vis`` frames old (``d_vis`` uniform in
``0..=d_vis_max``, clamped at the episode start), the action chunk ``t .. t+H-1`` (the last
action repeated past the episode's end), actions normalised by the dataset's mean/std. The
per-position flow time, the loss mask, the model input and the target come from the ``pir2``
package (``TrainSchedule.for_policy``, ``Draws.build``): the same draws as pir2's trainer.

The output directory is an ONNX checkpoint pir2 runs with ONNX Runtime::

    OUT/model.onnx      pir2's graph contract: x [B,H,A], tau [B,H], obs_fast [B,n_obs,F]
                        (raw; normalised inside the graph), obs_slow [B,S], d_vis [B] -> v
    OUT/stats.json      normalisation statistics, as pir2 computes and stores them
    OUT/identity.json   the policy trained as, SHA-256 of model.onnx

    pir2 eval ballplate --checkpoint OUT --policy pir2
"""

import argparse
import hashlib
import json
import math
import pathlib

import numpy as np
import pir2
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from torch import nn


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="LeRobotDataset v3.0 root directory")
    p.add_argument("--out", required=True, help="output directory (must not exist)")
    p.add_argument("--policy", default="pi_r2",
                   help="policy (training schedule): pi_r2, pi_r2_hidden, pi_r2_full, rtc, flow")
    p.add_argument("--recipe", default="{}", help='JSON of pir2 Recipe overrides, e.g. {"nfe": 2}')
    # The model's spec; the defaults are pir2's ball-on-plate spec (pir2-cli study/ballplate.rs).
    p.add_argument("--fast-keys", nargs="+", default=["observation.state"])
    p.add_argument("--slow-keys", nargs="*", default=["observation.environment_state"])
    p.add_argument("--action-key", default="action")
    p.add_argument("--horizon", type=int, default=16)
    p.add_argument("--n-obs", type=int, default=2)
    p.add_argument("--d-vis-max", type=int, default=3)
    # Network and optimiser (ours, not pir2's).
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--depth", type=int, default=3)
    p.add_argument("--tau-freqs", type=int, default=4)
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--batch-size", type=int, default=128)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args()


def load_episodes(root, fast_keys, slow_keys, action_key):
    """Per-episode (fast [T,F], slow [T,S], action [T,A]) float32 arrays, via LeRobot."""
    ds = LeRobotDataset(repo_id="local/" + pathlib.Path(root).name, root=root)
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


class Sampler:
    """Training samples built like pir2's batcher (see the module docstring)."""

    def __init__(self, episodes, stats, horizon, n_obs, d_vis_max, seed):
        self.eps_ = episodes
        self.h, self.n_obs, self.d_vis_max = horizon, n_obs, d_vis_max
        self.cum = np.cumsum([len(a) for _, _, a in episodes])
        self.a_mean = np.asarray(stats["action"]["mean"], np.float32)
        self.a_std = np.asarray(stats["action"]["std"], np.float32)
        self.rng = np.random.default_rng(seed)

    def batch(self, b):
        fast, slow, act, dvis = [], [], [], []
        for k in self.rng.integers(0, self.cum[-1], size=b):
            e = int(np.searchsorted(self.cum, k, side="right"))
            t = int(k - (self.cum[e - 1] if e else 0))
            f, s, a = self.eps_[e]
            hist = [max(t + j + 1 - self.n_obs, 0) for j in range(self.n_obs)]
            dv = int(self.rng.integers(0, self.d_vis_max + 1))
            chunk = [min(t + p, len(a) - 1) for p in range(self.h)]
            fast.append(f[hist])
            slow.append(s[max(t - dv, 0)])
            act.append((a[chunk] - self.a_mean) / self.a_std)
            dvis.append(dv)
        return (
            np.stack(fast).astype(np.float32),
            np.stack(slow).astype(np.float32),
            np.stack(act).astype(np.float32),
            np.asarray(dvis, np.int64),
        )


class FlowMLP(nn.Module):
    """A velocity MLP with pir2's observation normalisation inside (the graph takes raw obs).

    Input: the noisy chunk, per-position τ features (τ, sin πkτ, cos πkτ; a hidden front's
    τ = -1 passes through the same features), the fast history encoded as pir2 encodes it
    ([norm(o_t), norm_d(o_t - o_{t-1}), ...]), the normalised slow features and a one-hot of
    the clamped slow-feature age d_vis.
    """

    def __init__(self, stats, horizon, action_dim, n_obs, fast_dim, slow_dim, d_vis_max,
                 width, depth, tau_freqs):
        super().__init__()
        self.h, self.a, self.n_obs, self.d_vis_max = horizon, action_dim, n_obs, d_vis_max
        t = lambda v: torch.tensor(v, dtype=torch.float32)  # noqa: E731
        self.register_buffer("fast_mean", t(stats["fast"]["mean"]))
        self.register_buffer("fast_std", t(stats["fast"]["std"]))
        self.register_buffer("diff_mean", t(stats["fast_diff"]["mean"]))
        self.register_buffer("diff_std", t(stats["fast_diff"]["std"]))
        self.register_buffer("slow_mean", t(stats["slow"]["mean"]))
        self.register_buffer("slow_std", t(stats["slow"]["std"]))
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


def main():
    args = parse_args()
    out = pathlib.Path(args.out)
    if out.exists():
        raise SystemExit(f"{out} already exists; choose another --out")
    torch.manual_seed(args.seed)
    ds, episodes = load_episodes(args.data, args.fast_keys, args.slow_keys, args.action_key)
    fast_dim, slow_dim, action_dim = (episodes[0][i].shape[1] for i in range(3))
    n_frames = sum(len(a) for _, _, a in episodes)
    print(f"{args.data}: {len(episodes)} episodes, {n_frames} frames at {ds.fps} fps "
          f"(LeRobotDataset {ds.meta.info['codebase_version']}); "
          f"fast {fast_dim}, slow {slow_dim}, action {action_dim}")

    stats = compute_stats(episodes)
    sampler = Sampler(episodes, stats, args.horizon, args.n_obs, args.d_vis_max, args.seed)
    # The schedule pir2 trains this policy with, drawn by pir2's own (Rust) code.
    schedule = pir2.TrainSchedule.for_policy(args.policy, json.loads(args.recipe))
    draw_rng = pir2.Rng(args.seed)
    noise = np.random.default_rng(args.seed + 1)

    model = FlowMLP(stats, args.horizon, action_dim, args.n_obs, fast_dim, slow_dim,
                    args.d_vis_max, args.width, args.depth, args.tau_freqs)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    warmup = max(args.steps // 20, 1)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min((s + 1) / warmup, 0.5 * (1 + math.cos(math.pi * s / args.steps)))
    )
    for step in range(1, args.steps + 1):
        fast, slow, act, dvis = sampler.batch(args.batch_size)
        eps = noise.standard_normal(act.shape).astype(np.float32)
        d = schedule.draw(args.batch_size, args.horizon, draw_rng)
        x, tau_in, target = d.build(act, eps)
        v = model(torch.from_numpy(x), torch.from_numpy(tau_in), torch.from_numpy(fast),
                  torch.from_numpy(slow), torch.from_numpy(dvis))
        mask = torch.from_numpy(d.mask).unsqueeze(-1)
        # pir2's loss: Σ_p mask_p·|v_p − target_p|² / (A·Σ_p mask_p)
        loss = (mask * (v - torch.from_numpy(target)) ** 2).sum() / (action_dim * mask.sum())
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        if step % 100 == 0 or step == args.steps:
            print(f"step {step}/{args.steps}, loss {loss.item():.4f}")

    # Export to pir2's ONNX contract: dynamic batch, every other size fixed.
    model.eval()
    out.mkdir(parents=True)
    fast, slow, act, dvis = sampler.batch(2)
    d = schedule.draw(2, args.horizon, draw_rng)
    x, tau_in, _ = d.build(act, noise.standard_normal(act.shape).astype(np.float32))
    example = tuple(torch.from_numpy(a) for a in (x, tau_in, fast, slow, dvis))
    names = ["x", "tau", "obs_fast", "obs_slow", "d_vis"]
    torch.onnx.export(
        model, example, str(out / "model.onnx"), input_names=names, output_names=["v"],
        dynamic_axes={n: {0: "batch"} for n in names + ["v"]}, opset_version=17, dynamo=False,
    )
    # The exported graph must compute what the torch module computes.
    import onnxruntime as ort

    sess = ort.InferenceSession(str(out / "model.onnx"), providers=["CPUExecutionProvider"])
    got = sess.run(["v"], {n: a.numpy() for n, a in zip(names, example)})[0]
    with torch.no_grad():
        want = model(*example).numpy()
    err = float(np.abs(got - want).max())
    assert err < 1e-4, f"ONNX Runtime and torch differ by {err}"
    print(f"ONNX Runtime matches torch (max |diff| {err:.2e})")

    (out / "stats.json").write_text(json.dumps(stats, indent=2))
    sha = hashlib.sha256((out / "model.onnx").read_bytes()).hexdigest()
    (out / "identity.json").write_text(json.dumps({"policy": args.policy, "weights_sha256": sha}))
    cli_name = args.policy.replace("pi_r2", "pir2").replace("_", "-")  # pir2's --policy name
    print(f"wrote {out}/model.onnx, stats.json, identity.json; run it with\n"
          f"  pir2 eval ballplate --checkpoint {out} --policy {cli_name}")


if __name__ == "__main__":
    main()
