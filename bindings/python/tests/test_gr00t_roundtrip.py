"""PyTorch → pir2 round trip of a GR00T N1.7-shaped head in the per-position form.

A head (``pir2 gr00t example``'s N1.7-shaped weights, loaded into the PyTorch module of
``n17_reference.py``) is converted with ``pir2.gr00t.to_per_position``, fine-tuned a few steps
in PyTorch with the package's πR² draws, saved with GR00T's tensor names, exported by
``pir2 gr00t export`` and run by ``pir2 run gr00t-xarm-xhand --emulate --record-nfe``. The
first recorded NFE's velocity must equal the PyTorch forward on the recorded inputs within
1e-4.

Needs torch, diffusers, safetensors and a pir2 binary built with feature ``gr00t`` named by
``PIR2_BIN`` (``scripts/check-extra.sh torch`` sets all of that up); skipped otherwise.
"""

import json
import os
import pathlib
import shutil
import subprocess

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")
st = pytest.importorskip("safetensors.torch")

import pir2  # noqa: E402
from pir2 import gr00t as pg  # noqa: E402

from n17_reference import ActionHead  # noqa: E402

BIN = os.environ.get("PIR2_BIN")
pytestmark = pytest.mark.skipif(
    not BIN, reason="PIR2_BIN (a pir2 built with --features gr00t) is not set"
)


def pir2_cmd(*args, cwd=None):
    r = subprocess.run([BIN, *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=600)
    assert r.returncode == 0, f"pir2 {' '.join(map(str, args))} failed:\n{r.stdout}\n{r.stderr}"
    return r


def test_pytorch_fine_tune_runs_in_pir2_with_the_same_first_nfe(tmp_path: pathlib.Path):
    ex = tmp_path / "example"
    pir2_cmd("gr00t", "example", ex)
    emb = (ex / "embodiment.toml").read_text()
    horizon = int(next(l.split("=")[1] for l in emb.splitlines() if l.startswith("horizon")))
    d_max = int(next(l.split("=")[1] for l in emb.splitlines() if l.startswith("d_max")))

    # 1. the base head in PyTorch, converted and fine-tuned with pir2's draws
    torch.manual_seed(0)
    head, cfg = ActionHead.from_checkpoint(ex / "head" / "config.json", ex / "head" / "model.safetensors")
    sched = pir2.TrainSchedule.for_policy("pi_r2", {"nfe": 2, "pir2_d_max": d_max})
    pg.to_per_position(head, horizon, schedule=sched, seed=0)
    head.train()
    opt = torch.optim.AdamW(head.parameters(), lr=3e-3)
    b, t, d_vl = 4, 96, cfg["backbone_embedding_dim"]
    g = torch.Generator().manual_seed(1)
    image = torch.zeros(b, t, dtype=torch.bool)
    image[:, :64] = True
    bo = {"backbone_features": torch.randn(b, t, d_vl, generator=g), "image_mask": image,
          "backbone_attention_mask": torch.ones(b, t, dtype=torch.bool)}
    ai = {"state": torch.randn(b, 1, cfg["max_state_dim"], generator=g),
          "embodiment_id": torch.full((b,), 10, dtype=torch.long),
          "action": torch.randn(b, horizon, cfg["max_action_dim"], generator=g),
          "action_mask": torch.ones(b, horizon, cfg["max_action_dim"])}
    ai["action_mask"][..., 18:] = 0
    losses = []
    for _ in range(4):
        out = head(bo, ai)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(out["loss"].item())
    assert all(np.isfinite(losses)), losses
    head.eval()
    w = head.model.proj_out_1_heads.weight.detach()
    assert (w[1] - w[-1]).abs().max() > 1e-5, "the heads did not specialise"

    # 2. saved as a pir2 gr00t train step (GR00T's names under `action_head.`), exported
    run = tmp_path / "run"
    step = run / "step-000004"
    step.mkdir(parents=True)
    shutil.copy(ex / "head" / "config.json", step / "config.json")
    sd = {f"action_head.{k}": v.detach().contiguous() for k, v in head.state_dict().items()}
    st.save_file(sd, str(step / "model.safetensors"))
    for f in ("statistics.json", "embodiment.toml"):
        shutil.copy(ex / f, run / f)
    ck = tmp_path / "checkpoint"
    pir2_cmd("gr00t", "export", step, "--out", ck)
    for f in ("onnx/backbone.onnx", "tokenizer.json", "tokenizer_config.json", "embodiment_id.json"):
        (ck / f).parent.mkdir(exist_ok=True)
        if not (ck / f).exists():
            shutil.copy(ex / f, ck / f)

    # 3. run on the emulators, recording the first NFE
    rec = tmp_path / "nfe"
    pir2_cmd("gr00t", "run", "gr00t-xarm-xhand", "--checkpoint", ck, "--task", "catch the book",
             "--emulate", "--seconds", "2", "--record-nfe", rec, "--record-calls", "1")
    nfe = st.load_file(str(rec / "nfe-0000.safetensors"))
    bo1 = {"backbone_features": nfe["vl_embs"],
           "image_mask": nfe["image_mask"].bool(),
           "backbone_attention_mask": nfe["backbone_attention_mask"].bool()}
    ai1 = {"state": nfe["state"], "embodiment_id": nfe["embodiment_id"]}
    with torch.no_grad():
        v = pg.velocity(head, bo1, ai1, nfe["actions"], nfe["tau"], nfe["d_vis"],
                        backbone_processed=True)
    a = nfe["velocity"].shape[-1]
    got, want = v[..., :a], nfe["velocity"]
    err = float((got - want).abs().max())
    scale = max(1.0, float(want.abs().max()))
    print(f"first NFE: max |PyTorch - pir2| = {err:.3e} (velocity scale {scale:.3f}), "
          f"losses {['%.4f' % l for l in losses]}")
    assert err <= 1e-4 * scale, f"first NFE differs by {err}"
    # the recorded timesteps are pir2's map of the recorded τ
    np.testing.assert_array_equal(
        nfe["timesteps"].numpy(), pg.timestep_buckets(nfe["tau"], 1000).numpy()
    )
    json.dumps({"err": err})
