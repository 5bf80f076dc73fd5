#!/usr/bin/env python3
"""How smooth are a LeRobot v3 dataset's actions? (the Leap study's demonstrations)

Usage: demo-smoothness.py DATASET [--lags 1,2,3,4,6] [--windows 5,25] [--all-episodes]

Reads `DATASET/data/chunk-*/file-*.parquet` (the `action`, `episode_index`, `frame_index` and
`next.success` columns; `pir2 collect leap-cube` writes them) and prints, for each lag `k`
(control ticks), over all pairs `(a_t, a_{t+k})` inside one episode:

- `corr`: the Pearson correlation of `a_t` and `a_{t+k}`, per action dimension, averaged over
  the dimensions. 1 means an action `k` ticks old is as good as a fresh one (linearly); 0 means
  it carries nothing about the current one.
- `rel_change`: `E|a_{t+k} - a_t|^2 / (2 E|a - mean|^2)` (the normalised variogram; 0 for a
  constant action, 1 for independent draws, above 1 when the actions alternate).

For each window `w` it prints the share of the action variance left in the `w`-tick moving
average (inside one episode): about `1/w` for actions uncorrelated from tick to tick, near 1
for smooth ones. It also prints the share of action entries at the bound (`|a| >= 0.99`, where `tanh` saturates:
bang-bang control is not smooth) and the mean `|a|`. By default only the episodes that reach
the goal count (the ones `pir2 train` learns from); `--all-episodes` takes every episode.

Needs `pyarrow` and `numpy` (both in `.native/venv` after `scripts/setup-native.sh`).
Reads only; writes nothing.
"""
import glob
import os
import sys

import numpy as np
import pyarrow.parquet as pq


def fail(msg):
    print(f"demo-smoothness: {msg}", file=sys.stderr)
    sys.exit(2)


def parse_args(argv):
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        sys.exit(0 if argv else 2)
    root, lists, all_episodes = argv[0], {"--lags": [1, 2, 3, 4, 6], "--windows": [5, 25]}, False
    rest = argv[1:]
    while rest:
        flag = rest.pop(0)
        if flag == "--all-episodes":
            all_episodes = True
        elif flag in lists:
            if not rest:
                fail(f"{flag} needs a value, e.g. {flag} 1,2,4")
            value = rest.pop(0)
            try:
                lists[flag] = [int(x) for x in value.split(",")]
            except ValueError:
                fail(f"{flag}: '{value}' is not a comma-separated list of integers")
            if any(k < 1 for k in lists[flag]):
                fail(f"{flag}: every value must be at least 1 tick, got '{value}'")
        else:
            fail(
                f"unknown argument '{flag}' "
                "(usage: demo-smoothness.py DATASET [--lags 1,2] [--windows 5,25] [--all-episodes])"
            )
    return root, lists["--lags"], lists["--windows"], all_episodes


def load(root):
    files = sorted(glob.glob(os.path.join(root, "data", "chunk-*", "file-*.parquet")))
    if not files:
        fail(f"{root}: no data/chunk-*/file-*.parquet (is it a LeRobot v3 dataset?)")
    cols = ["action", "episode_index", "frame_index", "next.success"]
    episodes = {}
    for f in files:
        table = pq.read_table(f)
        missing = [c for c in cols if c not in table.column_names]
        if missing:
            fail(f"{f}: missing column(s) {', '.join(missing)}")
        action = np.asarray(table.column("action").to_pylist(), dtype=np.float64)
        ep = table.column("episode_index").to_numpy()
        frame = table.column("frame_index").to_numpy()
        success = table.column("next.success").to_numpy(zero_copy_only=False)
        for e in np.unique(ep):
            sel = ep == e
            entry = episodes.setdefault(int(e), ([], [], []))
            entry[0].append(frame[sel])
            entry[1].append(action[sel])
            entry[2].append(success[sel])
    out = {}
    for e, (frames, actions, successes) in episodes.items():
        frames = np.concatenate(frames)
        order = np.argsort(frames, kind="stable")
        frames = frames[order]
        if not np.array_equal(frames, np.arange(len(frames))):
            fail(f"episode {e}: frame_index is not 0..{len(frames) - 1} without gaps")
        out[e] = (np.concatenate(actions)[order], bool(np.concatenate(successes).any()))
    return out


def main():
    root, lags, windows, all_episodes = parse_args(sys.argv[1:])
    episodes = load(root)
    used = [a for a, ok in episodes.values() if ok or all_episodes]
    if not used:
        fail(f"{root}: no episode reaches the goal (use --all-episodes to take them all)")
    stacked = np.concatenate(used)
    mean = stacked.mean(axis=0)
    var = stacked.var(axis=0)
    print(
        f"{root}: {len(used)} of {len(episodes)} episodes "
        f"({'all' if all_episodes else 'those reaching the goal'}), {len(stacked)} frames, "
        f"{stacked.shape[1]}-d actions"
    )
    print(f"mean |a| {np.abs(stacked).mean():.3f}; entries at the bound (|a| >= 0.99) {np.mean(np.abs(stacked) >= 0.99):.3f}")
    print("lag (ticks) | corr  | rel_change | pairs")
    for k in lags:
        x = np.concatenate([a[:-k] for a in used if len(a) > k])
        y = np.concatenate([a[k:] for a in used if len(a) > k])
        xc, yc = x - x.mean(axis=0), y - y.mean(axis=0)
        denom = np.sqrt((xc**2).sum(axis=0) * (yc**2).sum(axis=0))
        ok = denom > 0
        corr = float(((xc * yc).sum(axis=0)[ok] / denom[ok]).mean())
        rel = float(((y - x) ** 2).sum(axis=1).mean() / (2.0 * var.sum()))
        print(f"{k:>11} | {corr:>5.3f} | {rel:>10.3f} | {len(x)}")
    print("window (ticks) | variance share of the moving average")
    for w in windows:
        kernel = np.ones(w) / w
        smooth = [
            np.stack([np.convolve(a[:, j], kernel, mode="valid") for j in range(a.shape[1])], axis=1)
            for a in used
            if len(a) >= w
        ]
        share = float(((np.concatenate(smooth) - mean) ** 2).sum(axis=1).mean() / var.sum())
        print(f"{w:>14} | {share:.3f}")


if __name__ == "__main__":
    main()
