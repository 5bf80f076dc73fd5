"""pir2.gr00t on Isaac-GR00T's own DiT classes (``gr00t/model/modules/dit.py``).

``test_gr00t_torch.py`` converts an N1.7-shaped head written here (``n17_reference.py``); this
module converts heads whose DiT is Isaac-GR00T's real ``AlternateVLDiT`` / ``DiT`` (with its
``BasicTransformerBlock``, ``AdaLayerNorm``, ``TimestepEncoder``, ``CachedCrossAttnProcessor``
and ``CrossAttnKVCache``), put in ``head.model`` of the reference head in place of ours, with
N1.7's ``diffusion_model_cfg`` at tiny dimensions. Isaac-GR00T is not on PyPI, so this runs only
against a checkout::

    git clone https://github.com/NVIDIA/Isaac-GR00T
    cd bindings/python/tests
    PIR2_ISAAC_GR00T=/path/to/Isaac-GR00T python -m pytest -q test_gr00t_isaac.py

``dit.py`` is loaded by its file path (it imports only torch and diffusers); the ``gr00t``
package itself is not imported (its ``__init__`` pulls the whole training stack).
"""

import contextlib
import copy
import importlib.util
import io
import os
import pathlib
import sys
import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")

_ROOT = os.environ.get("PIR2_ISAAC_GR00T", "")
_DIT_PY = pathlib.Path(_ROOT) / "gr00t" / "model" / "modules" / "dit.py"
if not _ROOT or not _DIT_PY.is_file():
    pytest.skip(
        "the Isaac-GR00T check needs a checkout of NVIDIA/Isaac-GR00T: set PIR2_ISAAC_GR00T to "
        "the directory holding gr00t/model/modules/dit.py (e.g. `PIR2_ISAAC_GR00T=~/Isaac-GR00T "
        "python -m pytest test_gr00t_isaac.py`)"
        + (f"; {_DIT_PY} does not exist" if _ROOT else ""),
        allow_module_level=True,
    )

import pir2  # noqa: E402
from pir2 import gr00t as pg  # noqa: E402

from n17_reference import ActionHead  # noqa: E402
from test_gr00t_torch import A_MAX, H, config, inputs  # noqa: E402


def _load_dit():
    spec = importlib.util.spec_from_file_location("pir2_tests_isaac_gr00t_dit", _DIT_PY)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


isaac = _load_dit()

KINDS = ["AlternateVLDiT", "DiT"]
CFG = config()
D = CFG["diffusion_model_cfg"]["num_attention_heads"] * CFG["diffusion_model_cfg"]["attention_head_dim"]
LAYERS = CFG["diffusion_model_cfg"]["num_layers"]


def real_dit(kind):
    """Isaac-GR00T's DiT as ``Gr00tN1d7ActionHead.__init__`` builds it from the config."""
    c = CFG
    # its constructor prints the parameter count; diffusers warns about config attributes
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        if kind == "AlternateVLDiT":
            return isaac.AlternateVLDiT(
                **c["diffusion_model_cfg"],
                cross_attention_dim=c["backbone_embedding_dim"],
                attend_text_every_n_blocks=c["attend_text_every_n_blocks"],
            )
        return isaac.DiT(**c["diffusion_model_cfg"], cross_attention_dim=c["backbone_embedding_dim"])


def make_head(kind="AlternateVLDiT", seed=0):
    """The reference N1.7 head with Isaac-GR00T's DiT as ``model``; seeded, non-trivial weights."""
    torch.manual_seed(seed)
    head = ActionHead(CFG)
    head.model = real_dit(kind)
    assert type(head.model).__name__ == kind and type(head.model).__module__ == isaac.__name__
    with torch.no_grad():
        for p in head.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return head.eval()


def dit_kwargs(head, bo, sa, timestep, **extra):
    """The DiT call of ``Gr00tN1d7ActionHead.forward`` (``bo`` through ``process_backbone_output``)."""
    kw = dict(
        hidden_states=sa,
        encoder_hidden_states=bo["backbone_features"],
        encoder_attention_mask=bo["backbone_attention_mask"],
        timestep=timestep,
        return_all_hidden_states=True,
    )
    if getattr(head.model, "attend_text_every_n_blocks", None) is not None:
        kw["image_mask"] = bo["image_mask"]
        kw["backbone_attention_mask"] = bo["backbone_attention_mask"]
    kw.update(extra)
    return kw


def isaac_velocity(head, bo, ai, x, t):
    """GR00T N1.7's velocity with one timestep ``t [B]`` for every token, through the real DiT
    (the unconverted head; the computation of ``Gr00tN1d7ActionHead.forward``)."""
    bo = head.process_backbone_output(bo)
    b, h, _ = x.shape
    emb = ai["embodiment_id"]
    s = head.state_encoder(ai["state"].reshape(b, 1, -1), emb)
    a = head.action_encoder(x, t, emb) + head.position_embedding(torch.arange(h)).unsqueeze(0)
    y, _ = head.model(**dit_kwargs(head, bo, torch.cat([s, a], 1), t))
    return head.action_decoder(y, emb)[:, -h:]


def maxdiff(a, b):
    return float((a - b).abs().max())


def reldiff(a, b):
    """``max |a − b|`` relative to ``max(1, max |b|)``: DiT activations are O(1–10), where
    float32's spacing is 1e-7 to 1e-6, and a few units of it are rounding, not a bug."""
    return maxdiff(a, b) / max(1.0, float(b.abs().max()))


def norm1_outputs(dit):
    """Capture every block's AdaLN output (input and output) on the next forward."""
    seen, handles = {}, []
    for i, block in enumerate(dit.transformer_blocks):
        def hook(mod, args, out, i=i):
            seen[i] = (args[0].detach().clone(), out.detach().clone())
        handles.append(block.norm1.register_forward_hook(hook))
    return seen, handles


def token_timesteps(b, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 1000, (b, 1 + H), generator=g)


# (a) a position-uniform τ: the converted head computes what Isaac-GR00T's DiT computes
@pytest.mark.parametrize("kind", KINDS)
def test_uniform_tau_equals_the_real_dit(kind):
    base = make_head(kind)
    bo, ai, x = inputs()
    worst_v = worst_dit = 0.0
    for t in (0, 437, 999):
        tt = torch.tensor([t, t])
        conv = pg.to_per_position(copy.deepcopy(base), H, state_timestep=t).eval()
        assert isinstance(conv.model, type(base.model))
        with torch.no_grad():
            want = isaac_velocity(base, bo, ai, x, tt)
            tau = np.full((2, H), (t + 0.5) / 1000.0, np.float32)
            got = pg.velocity(conv, bo, ai, x, tau)
            worst_v = max(worst_v, maxdiff(got, want))
            # GR00T's own call (a shared timestep [B], all hidden states) on the converted DiT
            vl = base.process_backbone_output(bo)
            sa = torch.randn(2, 1 + H, D, generator=torch.Generator().manual_seed(t))
            y_base, hs_base = base.model(**dit_kwargs(base, vl, sa, tt))
            y_conv, hs_conv = conv.model(**dit_kwargs(conv, vl, sa, tt))
            assert len(hs_conv) == len(hs_base) == LAYERS + 1
            worst_dit = max(worst_dit, reldiff(y_conv, y_base), *(reldiff(a, b) for a, b in zip(hs_conv, hs_base)))
    print(f"\n[{kind}] uniform τ: max |velocity − Isaac-GR00T's| = {worst_v:.3g}; "
          f"DiT with GR00T's shared timestep, output and hidden states: {worst_dit:.3g} relative")
    # Not bit for bit: the timestep encoder runs on B·(1 + H) rows where GR00T's runs on B,
    # and the per-token heads are one batched matmul where GR00T's layer is one addmm; both
    # round differently in the last bits.
    assert worst_v <= 1e-6, worst_v
    assert worst_dit <= 1e-6, worst_dit


# (b) per-token timesteps reach the real blocks' AdaLN; one head modulates only its own token
def test_per_token_timesteps_reach_every_real_adaln():
    base = make_head()
    conv = pg.to_per_position(copy.deepcopy(base), H).eval()
    bo, _, _ = inputs()
    vl = base.process_backbone_output(bo)
    sa = torch.randn(2, 1 + H, D, generator=torch.Generator().manual_seed(7))
    ts = token_timesteps(2)
    seen, handles = norm1_outputs(conv.model)
    with torch.no_grad():
        y_tok, _ = conv.model(**dit_kwargs(conv, vl, sa, ts))
    for hnd in handles:
        hnd.remove()
    assert sorted(seen) == list(range(LAYERS))
    worst = 0.0
    with torch.no_grad():
        for i, block in enumerate(base.model.transformer_blocks):
            x_in, out = seen[i]
            for p in range(1 + H):
                # Isaac-GR00T's own AdaLayerNorm on token p alone, with token p's timestep
                temb = base.model.timestep_encoder(ts[:, p])
                want = block.norm1(x_in[:, p : p + 1], temb)[:, 0]
                worst = max(worst, reldiff(out[:, p], want))
        # and it is not the uniform answer
        y_uni, _ = conv.model(**dit_kwargs(conv, vl, sa, ts[:, 5]))
    print(f"\nper-token timesteps: max |AdaLN − Isaac-GR00T's AdaLayerNorm per token| = {worst:.3g} relative; "
          f"output moved {maxdiff(y_tok, y_uni):.3g} from the uniform-τ output")
    assert worst <= 1e-6, worst
    assert maxdiff(y_tok, y_uni) > 1e-3

    # one token's timestep changed: the first block's modulation changes at that token only
    q = 4
    ts2 = ts.clone()
    ts2[:, q] = (ts2[:, q] + 500) % 1000
    seen2, handles = norm1_outputs(conv.model)
    with torch.no_grad():
        conv.model(**dit_kwargs(conv, vl, sa, ts2))
    for hnd in handles:
        hnd.remove()
    d = (seen2[0][1] - seen[0][1]).abs().amax(dim=(0, 2))
    assert d[q] > 1e-3 and float(d[torch.arange(1 + H) != q].max()) == 0.0, d


def test_perturbing_one_head_changes_only_its_token():
    p = 5  # DiT token p = action position p − 1
    conv = pg.to_per_position(make_head(), H).eval()
    bo, ai, x = inputs()
    vl = conv.process_backbone_output(bo)
    sa = torch.randn(2, 1 + H, D, generator=torch.Generator().manual_seed(3))
    ts = token_timesteps(2, seed=1)
    tau = torch.rand(2, H, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        y0, _ = conv.model(**dit_kwargs(conv, vl, sa, ts))
        v0 = pg.velocity(conv, bo, ai, x, tau)
        seen0, handles = norm1_outputs(conv.model)
        conv.model(**dit_kwargs(conv, vl, sa, ts))
        for hnd in handles:
            hnd.remove()

        # the output modulation's head p: the DiT output moves at token p only
        heads = conv.model.proj_out_1_heads
        saved = heads.weight[p].clone()
        heads.weight[p] += 0.1 * torch.randn_like(saved)
        y1, _ = conv.model(**dit_kwargs(conv, vl, sa, ts))
        v1 = pg.velocity(conv, bo, ai, x, tau)
        heads.weight[p] = saved
        d = (y1 - y0).abs().amax(dim=(0, 2))
        assert d[p] > 1e-3 and float(d[torch.arange(1 + H) != p].max()) == 0.0, d
        dv = (v1 - v0).abs().amax(dim=(0, 2))
        assert dv[p - 1] > 1e-3 and float(dv[torch.arange(H) != p - 1].max()) == 0.0, dv

        # the first block's AdaLN head p: that block's modulation moves at token p only, and
        # attention carries it to the other tokens downstream
        lin = conv.model.transformer_blocks[0].norm1.linear_heads
        saved = lin.weight[p].clone()
        lin.weight[p] += 0.1 * torch.randn_like(saved)
        seen1, handles = norm1_outputs(conv.model)
        y2, _ = conv.model(**dit_kwargs(conv, vl, sa, ts))
        for hnd in handles:
            hnd.remove()
        lin.weight[p] = saved
    d = (seen1[0][1] - seen0[0][1]).abs().amax(dim=(0, 2))
    assert d[p] > 1e-3 and float(d[torch.arange(1 + H) != p].max()) == 0.0, d
    assert maxdiff(y2, y0) > 1e-4


# (c) Isaac-GR00T's inference path: the cross-attention K/V cache
def test_kv_cache_path_equals_the_uncached_one():
    base = make_head()
    conv = pg.to_per_position(copy.deepcopy(base), H).eval()
    bo, _, _ = inputs()
    vl = base.process_backbone_output(bo)
    cache = isaac.CrossAttnKVCache()
    cache_base = isaac.CrossAttnKVCache()
    g = torch.Generator().manual_seed(4)
    worst = worst_base = 0.0
    with torch.no_grad():
        for step in range(4):  # one denoising loop: the cache filled at step 0, read after
            sa = torch.randn(2, 1 + H, D, generator=g)
            ts = token_timesteps(2, seed=10 + step)
            y_cached, _ = conv.model(**dit_kwargs(conv, vl, sa, ts, kv_cache=cache))
            y_plain, _ = conv.model(**dit_kwargs(conv, vl, sa, ts))
            worst = max(worst, maxdiff(y_cached, y_plain))
            # GR00T's shared timestep with a cache, converted against the real class
            t = ts[:, 0]
            y_c, _ = conv.model(**dit_kwargs(conv, vl, sa, t, kv_cache=cache))
            y_b, _ = base.model(**dit_kwargs(base, vl, sa, t, kv_cache=cache_base))
            worst_base = max(worst_base, reldiff(y_c, y_b))
    cross = [i for i in range(LAYERS) if i % 2 == 0]
    assert sorted(cache) == cross and sorted(cache_base) == cross
    print(f"\nkv_cache: max |cached − uncached| = {worst:.3g}; "
          f"converted vs Isaac-GR00T's AlternateVLDiT, both cached, shared t: {worst_base:.3g} relative")
    assert worst == 0.0, worst
    assert worst_base <= 1e-6, worst_base


# (d) the tensors pir2's importer reads (docs/gr00t-import.md, "A πR² head fine-tuned in PyTorch")
@pytest.mark.parametrize("kind", KINDS)
def test_state_dict_has_the_names_pir2_imports(kind):
    conv = pg.to_per_position(make_head(kind), H, d_vis_max=5)
    sd = conv.state_dict()
    for i in range(LAYERS):
        pre = f"model.transformer_blocks.{i}.norm1"
        assert tuple(sd[f"{pre}.linear_heads.weight"].shape) == (1 + H, 2 * D, D)
        assert tuple(sd[f"{pre}.linear_heads.bias"].shape) == (1 + H, 2 * D)
        assert f"{pre}.linear.weight" not in sd and f"{pre}.linear.bias" not in sd
    assert tuple(sd["model.proj_out_1_heads.weight"].shape) == (1 + H, 2 * D, D)
    assert tuple(sd["model.proj_out_1_heads.bias"].shape) == (1 + H, 2 * D)
    assert "model.proj_out_1.weight" not in sd and "model.proj_out_1.bias" not in sd
    assert tuple(sd["delay_embedding.weight"].shape) == (6, CFG["input_embedding_dim"])
    # the same tensors, by name and shape, as the reference head that test_gr00t_roundtrip.py
    # exports with pir2: nothing the importer would call unexpected
    ref = pg.to_per_position(ActionHead(CFG), H, d_vis_max=5).state_dict()
    assert {k: tuple(v.shape) for k, v in sd.items()} == {k: tuple(v.shape) for k, v in ref.items()}


# (e) the πR² training step through the real DiT, dropout on
@pytest.mark.parametrize("kind", KINDS)
def test_training_through_the_real_dit_specialises_every_head(kind):
    sched = pir2.TrainSchedule.for_policy("pi_r2", {"nfe": 2, "pir2_d_max": 3})
    head = pg.to_per_position(make_head(kind), H, schedule=sched, seed=3)
    head.train()
    b = 8
    bo, ai, x = inputs(b=b)
    with torch.no_grad():  # dropout is on: two evaluations differ
        tau = np.full((b, H), 0.5, np.float32)
        assert maxdiff(pg.velocity(head, bo, ai, x, tau), pg.velocity(head, bo, ai, x, tau)) > 0
    ai["action"] = torch.randn(b, H, A_MAX, generator=torch.Generator().manual_seed(5))
    ai["action_mask"] = torch.ones(b, H, A_MAX)
    layers = {f"block {i} norm1": blk.norm1.linear_heads for i, blk in enumerate(head.model.transformer_blocks)}
    layers["proj_out_1"] = head.model.proj_out_1_heads
    start = {k: m.weight.detach().clone() for k, m in layers.items()}
    reached = {k: torch.zeros(1 + H, dtype=torch.bool) for k in layers}
    opt = torch.optim.Adam(head.parameters(), lr=1e-2)
    torch.manual_seed(0)
    losses = []
    for _ in range(4):
        out = head(bo, ai)
        assert torch.isfinite(out["loss"]), out["loss"]
        losses.append(float(out["loss"].detach()))
        opt.zero_grad()
        out["loss"].backward()
        for k, m in layers.items():
            reached[k] |= (m.weight.grad.flatten(1).abs().sum(1) > 0) | (m.bias.grad.abs().sum(1) > 0)
        opt.step()
    for k in layers:
        if k == "proj_out_1":
            # the state token's output is dropped (pred[:, -H:]): its output head gets no
            # gradient, in GR00T as here; every action token's head does
            assert reached[k][1:].all() and not reached[k][0], (k, reached[k])
        else:
            assert reached[k].all(), (k, reached[k])
    # the heads specialise: after the steps no two trained heads of a layer are equal
    for k, m in layers.items():
        w = m.weight.detach()
        trained = range(1, 1 + H) if k == "proj_out_1" else range(1 + H)
        gap = min(maxdiff(w[p], w[q]) for p in trained for q in trained if p < q)
        assert gap > 1e-5, (k, gap)
        assert maxdiff(w[list(trained)], start[k][list(trained)]) > 1e-4
    print(f"\n[{kind}] 4 πR² steps, dropout on: losses {', '.join(f'{v:.4f}' for v in losses)}")
