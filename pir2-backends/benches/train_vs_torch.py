"""Training speed of pir2's candle U-Net next to PyTorch eager, measured in one run.

Both sides train the same network (Conditional U-Net 1D, kernel 5, per-position FiLM,
H = 16, A = 16, batch 256, AdamW, clipping) with the same thread count. The two are run
alternately, `--rounds` times each, so a change in the machine's load hits both; the
printed ratio is PyTorch's median seconds per step over candle's (> 1: candle is faster).

    cargo build --release -p pir2-backends --example train_speed
    python3 pir2-backends/benches/train_vs_torch.py \
        --candle target/release/examples/train_speed --torch-python <python with torch> \
        --widths 32,64,128 --widths 64,128,256 --threads 2
"""

import argparse
import re
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def candle_step(exe, widths, threads, steps):
    out = subprocess.run(
        [exe, "--widths", widths, "--path", "fused", "--steps", str(steps),
         "--threads", str(threads), "--nfe", "0"],
        check=True, capture_output=True, text=True,
    ).stdout
    m = re.search(r"fused\s+training step ([0-9.]+) s", out)
    if not m:
        sys.exit(f"no training step time in train_speed's output:\n{out}")
    return float(m.group(1))


def torch_step(python, widths, threads, steps):
    out = subprocess.run(
        [python, str(HERE / "torch_ref.py"), "--widths", widths, "--threads", str(threads),
         "--steps", str(steps), "--warmup", "2"],
        check=True, capture_output=True, text=True,
    ).stdout
    m = re.search(r": ([0-9.]+) s/step", out)
    if not m:
        sys.exit(f"no step time in torch_ref.py's output:\n{out}")
    return float(m.group(1)), out.split(" widths")[0]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--candle", required=True, help="the built train_speed example")
    ap.add_argument("--torch-python", required=True, help="a python with torch installed")
    ap.add_argument("--widths", action="append", help="U-Net widths, repeatable")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    for widths in args.widths or ["64,128,256"]:
        c, t, version = [], [], ""
        for _ in range(args.rounds):
            c.append(candle_step(args.candle, widths, args.threads, args.steps))
            s, version = torch_step(args.torch_python, widths, args.threads, args.steps)
            t.append(s)
        cm, tm = statistics.median(c), statistics.median(t)
        print(
            f"U-Net [{widths}] batch 256, {args.threads} threads, median of {args.rounds}: "
            f"candle {cm:.3f} s/step, {version} {tm:.3f} s/step, "
            f"PyTorch / candle = {tm / cm:.2f}"
        )
        print(f"  rounds: candle {['%.3f' % x for x in c]}, torch {['%.3f' % x for x in t]}")


if __name__ == "__main__":
    main()
