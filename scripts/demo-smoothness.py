#!/usr/bin/env python3
"""How smooth are a LeRobot v3 dataset's actions? (the Leap study's demonstrations)

Usage: demo-smoothness.py DATASET [--lags 1,2,3,4,6] [--windows 5,25] [--all-episodes]
       demo-smoothness.py --self-test

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
the goal and have at least 2 frames count (the ones `pir2 train` learns from);
`--all-episodes` takes every episode of at least 2 frames.

Needs `pyarrow` and `numpy` (both in `.native/venv` after `scripts/setup-native.sh`).
Reads only; writes nothing. `--self-test` writes white noise and a slow sine as a small dataset
in a temporary directory (two files, rows shuffled) and checks the loader and both measures on
them; the native CI runs it.
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


def lag_stats(used, var, k):
    """(corr, rel_change, pairs) of `a_t` against `a_{t+k}` inside each episode."""
    x = np.concatenate([a[:-k] for a in used if len(a) > k])
    y = np.concatenate([a[k:] for a in used if len(a) > k])
    xc, yc = x - x.mean(axis=0), y - y.mean(axis=0)
    denom = np.sqrt((xc**2).sum(axis=0) * (yc**2).sum(axis=0))
    ok = denom > 0
    corr = float(((xc * yc).sum(axis=0)[ok] / denom[ok]).mean())
    rel = float(((y - x) ** 2).sum(axis=1).mean() / (2.0 * var.sum()))
    return corr, rel, len(x)


def window_share(used, mean, var, w):
    """Share of the action variance left in the `w`-tick moving average inside each episode."""
    kernel = np.ones(w) / w
    smooth = [
        np.stack([np.convolve(a[:, j], kernel, mode="valid") for j in range(a.shape[1])], axis=1)
        for a in used
        if len(a) >= w
    ]
    return float(((np.concatenate(smooth) - mean) ** 2).sum(axis=1).mean() / var.sum())


def self_test():
    """Known signals through a real parquet round trip: white noise and a slow sine."""
    import tempfile

    import pyarrow as pa

    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as root:
        chunk = os.path.join(root, "data", "chunk-000")
        os.makedirs(chunk)
        rows = []
        for e in range(4):
            n = 2000
            white = rng.uniform(-1, 1, size=(n, 2))
            slow = np.sin(2 * np.pi * np.arange(n) / 400.0 + e)[:, None] * np.ones((1, 2))
            action = np.concatenate([white, slow], axis=1) if e < 2 else np.concatenate([slow, slow], axis=1)
            for t in range(n):
                rows.append((e, t, action[t], e != 3))
        rng.shuffle(rows)  # files and rows out of order: the loader must sort them
        half = len(rows) // 2
        for i, part in enumerate((rows[:half], rows[half:])):
            table = pa.table(
                {
                    "action": pa.array([r[2].astype(np.float32).tolist() for r in part], pa.list_(pa.float32(), 4)),
                    "episode_index": pa.array([r[0] for r in part], pa.int64()),
                    "frame_index": pa.array([r[1] for r in part], pa.int64()),
                    "next.success": pa.array([r[3] for r in part], pa.bool_()),
                }
            )
            pq.write_table(table, os.path.join(chunk, f"file-{i:03d}.parquet"))
        episodes = load(root)
        assert sorted(episodes) == [0, 1, 2, 3], sorted(episodes)
        assert [episodes[e][1] for e in range(4)] == [True, True, True, False]
        white = [episodes[e][0][:, :2] for e in (0, 1)]
        slow = [episodes[e][0][:, 2:] for e in (0, 1)]
        for used, lag1, share5 in ((white, (-0.05, 0.05), (0.17, 0.23)), (slow, (0.99, 1.0), (0.99, 1.01))):
            stacked = np.concatenate(used)
            corr, rel, _ = lag_stats(used, stacked.var(axis=0), 1)
            share = window_share(used, stacked.mean(axis=0), stacked.var(axis=0), 5)
            assert lag1[0] <= corr <= lag1[1], (corr, lag1)
            assert share5[0] <= share <= share5[1], (share, share5)
            assert (rel > 0.9) == (lag1[1] < 0.5), rel
    print("demo-smoothness self-test: ok")


def main():
    if sys.argv[1:] == ["--self-test"]:
        self_test()
        return
    root, lags, windows, all_episodes = parse_args(sys.argv[1:])
    episodes = load(root)
    # The episodes `pir2 train` learns from: those reaching the goal, at least 2 frames long.
    used = [a for a, ok in episodes.values() if (ok or all_episodes) and len(a) >= 2]
    if not used:
        fail(f"{root}: no episode reaches the goal (use --all-episodes to take them all)")
    stacked = np.concatenate(used)
    mean = stacked.mean(axis=0)
    var = stacked.var(axis=0)
    print(
        f"{root}: {len(used)} of {len(episodes)} episodes "
        f"({'all' if all_episodes else 'those reaching the goal'}; at least 2 frames), "
        f"{len(stacked)} frames, "
        f"{stacked.shape[1]}-d actions"
    )
    at_bound = np.mean(np.abs(stacked) >= 0.99)
    print(f"mean |a| {np.abs(stacked).mean():.3f}; entries at the bound (|a| >= 0.99) {at_bound:.3f}")
    print("lag (ticks) | corr  | rel_change | pairs")
    for k in lags:
        corr, rel, pairs = lag_stats(used, var, k)
        print(f"{k:>11} | {corr:>5.3f} | {rel:>10.3f} | {pairs}")
    print("window (ticks) | variance share of the moving average")
    for w in windows:
        print(f"{w:>14} | {window_share(used, mean, var, w):.3f}")


if __name__ == "__main__":
    main()
