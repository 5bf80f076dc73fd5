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

The network, the loss and the export are those of the LeRobot policy plugin
``lerobot_policy_pir2_flow`` (``lerobot_policy_pir2_flow.flow``; install it with
``pip install --no-deps -e examples/lerobot-flow/lerobot_policy_pir2_flow``); this script
keeps pir2's own way of cutting samples (a frame drawn uniformly with replacement, the
slow-feature age drawn per sample) in place of LeRobot's data loader and ``lerobot-train``.
"""

import argparse
import json
import math
import pathlib

import numpy as np
import pir2
import torch
from lerobot_policy_pir2_flow.flow import (
    FlowMLP,
    cli_policy_name,
    compute_stats,
    export_checkpoint,
    flow_loss,
    load_episodes,
)


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
        loss = flow_loss(model, d, act, eps, fast, slow, dvis)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        if step % 100 == 0 or step == args.steps:
            print(f"step {step}/{args.steps}, loss {loss.item():.4f}")

    # Export to pir2's ONNX contract (checked with ONNX Runtime against the torch module).
    fast, slow, act, dvis = sampler.batch(2)
    d = schedule.draw(2, args.horizon, draw_rng)
    x, tau_in, _ = d.build(act, noise.standard_normal(act.shape).astype(np.float32))
    example = tuple(torch.from_numpy(a) for a in (x, tau_in, fast, slow, dvis))
    err = export_checkpoint(model, out, args.policy, stats, example=example)
    print(f"ONNX Runtime matches torch (max |diff| {err:.2e})")
    print(f"wrote {out}/model.onnx, stats.json, identity.json; run it with\n"
          f"  pir2 eval ballplate --checkpoint {out} --policy {cli_policy_name(args.policy)}")


if __name__ == "__main__":
    main()
