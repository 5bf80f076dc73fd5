"""PyTorch eager reference for the U-Net training-step benchmark (`benches/latency.rs`).

The same network as pir2's candle U-Net (conditional U-Net 1D, per-position FiLM, nearest x2 +
conv3 up-sampling, stride-2 conv3 down-sampling, GroupNorm + Mish conv blocks), the same
conditioning layout (sinusoidal tau embedding of width E plus a hidden flag -> MLP; shared
vector [mish(mean embedding), encoded fast history, slow features, d_vis embedding]), the
same loss (masked per-position MSE), optimiser (AdamW, betas 0.95/0.999, weight decay 1e-6)
and gradient clipping (global norm 1.0), batch 256, H = 16, A = 16, fast history 2 x 32,
slow 9, d_vis_max 5, on random inputs. Prints seconds per step after warm-up.

    python3 -m venv /tmp/torchvenv && /tmp/torchvenv/bin/pip install torch==2.13.0
    /tmp/torchvenv/bin/python pir2-backends/benches/torch_ref.py --widths 64,128,256 --threads 2
"""

import argparse
import math
import time

import torch
import torch.nn as nn
import torch.nn.functional as F


class ConvBlock(nn.Module):
    def __init__(self, cin, cout, k, groups):
        super().__init__()
        self.conv = nn.Conv1d(cin, cout, k, padding=k // 2)
        self.gn = nn.GroupNorm(groups, cout)

    def forward(self, x):
        return F.mish(self.gn(self.conv(x)))


class Res(nn.Module):
    def __init__(self, cin, cout, k, groups, cs, e):
        super().__init__()
        self.b0 = ConvBlock(cin, cout, k, groups)
        self.b1 = ConvBlock(cout, cout, k, groups)
        self.film = nn.Linear(cs, 2 * cout)
        self.film_pos = nn.Linear(e, 2 * cout)
        self.res = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()
        self.cout = cout

    def forward(self, x, shared, pos):
        out = self.b0(x)
        f = self.film(shared)[:, :, None] + self.film_pos(pos).transpose(1, 2)
        scale, bias = f[:, : self.cout], f[:, self.cout :]
        out = self.b1(out * (1 + scale) + bias)
        return out + self.res(x)


class UNet(nn.Module):
    def __init__(self, widths, a=16, k=5, groups=8, e=64, fe=64, sw=9, dvis_max=5, dd=16):
        super().__init__()
        cs = e + fe + sw + dd
        self.e = e
        self.tau_mlp = nn.Sequential(nn.Linear(e + 1, 4 * e), nn.Mish(), nn.Linear(4 * e, e))
        self.dvis = nn.Embedding(dvis_max + 1, dd)
        dims = [a] + list(widths)
        n = len(widths)
        self.down = nn.ModuleList()
        for i in range(n):
            din, dout = dims[i], dims[i + 1]
            self.down.append(
                nn.ModuleList(
                    [
                        Res(din, dout, k, groups, cs, e),
                        Res(dout, dout, k, groups, cs, e),
                        nn.Conv1d(dout, dout, 3, stride=2, padding=1) if i + 1 < n else nn.Identity(),
                    ]
                )
            )
        w = widths[-1]
        self.mid = nn.ModuleList([Res(w, w, k, groups, cs, e), Res(w, w, k, groups, cs, e)])
        self.up = nn.ModuleList()
        for i in reversed(range(1, n)):
            din, dout = dims[i], dims[i + 1]
            self.up.append(
                nn.ModuleList(
                    [
                        Res(2 * dout, din, k, groups, cs, e),
                        Res(din, din, k, groups, cs, e),
                        nn.Conv1d(din, din, 3, padding=1),
                    ]
                )
            )
        self.final_block = ConvBlock(widths[0], widths[0], k, groups)
        self.final_conv = nn.Conv1d(widths[0], a, 1)
        half = e // 2
        step = math.log(10000.0) / (half - 1)
        self.register_buffer("freqs", torch.exp(-step * torch.arange(half, dtype=torch.float32)))

    def forward(self, x, tau, fast, slow, dvis):
        # x [B, H, A], tau [B, H] (clamped, hidden flag separate), fast [B, 64], slow [B, 9].
        b, h, _ = x.shape
        s = tau[..., None] * 1000.0 * self.freqs
        flag = torch.zeros_like(tau)[..., None]
        sin = torch.cat([s.sin(), s.cos(), flag], -1)
        emb = self.tau_mlp(sin)  # [B, H, E]
        shared = torch.cat([F.mish(emb.mean(1)), fast, slow, self.dvis(dvis)], 1)
        pos = F.mish(emb)
        pooled = [pos]
        for i in range(1, len(self.down)):
            l = h >> i
            pooled.append(pos.reshape(b, l, h // l, -1).mean(2))
        x = x.transpose(1, 2)
        skips = []
        for i, (r0, r1, ds) in enumerate(self.down):
            x = r0(x, shared, pooled[i])
            x = r1(x, shared, pooled[i])
            skips.append(x)
            x = ds(x)
        for m in self.mid:
            x = m(x, shared, pooled[-1])
        n = len(self.down)
        for j, (r0, r1, us) in enumerate(self.up):
            lvl = n - 1 - j
            x = torch.cat([x, skips[lvl]], 1)
            x = r0(x, shared, pooled[lvl])
            x = r1(x, shared, pooled[lvl])
            x = us(F.interpolate(x, scale_factor=2, mode="nearest"))
        y = self.final_conv(self.final_block(x))
        return y.transpose(1, 2)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--widths", default="64,128,256")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--batch", type=int, default=256)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    widths = [int(w) for w in args.widths.split(",")]
    model = UNet(widths)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, betas=(0.95, 0.999), eps=1e-8, weight_decay=1e-6)
    b, h, a = args.batch, 16, 16

    def step():
        x = torch.randn(b, h, a)
        tau = torch.rand(b, h)
        fast = torch.randn(b, 64)
        slow = torch.randn(b, 9)
        dvis = torch.randint(0, 6, (b,))
        target = torch.randn(b, h, a)
        mask = (torch.rand(b, h, 1) > 0.1).float()
        v = model(x, tau, fast, slow, dvis)
        loss = ((v - target) ** 2 * mask).sum() / (mask.sum().clamp(min=1.0) * a)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        return loss.item()

    for _ in range(args.warmup):
        step()
    t, c = time.perf_counter(), time.process_time()
    for _ in range(args.steps):
        step()
    dt = (time.perf_counter() - t) / args.steps
    dc = (time.process_time() - c) / args.steps
    n_params = sum(p.numel() for p in model.parameters())
    print(
        f"torch {torch.__version__} widths {widths} batch {b} threads {args.threads}: "
        f"{dt:.3f} s/step ({1 / dt:.2f} steps/s, {n_params} parameters); "
        f"process CPU time {dc:.3f} s/step"
    )


if __name__ == "__main__":
    main()
