"""pir2.gr00t: GR00T N1.7's head in the per-position form (needs torch and diffusers; skipped
without them)."""

import copy

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("diffusers")

import pir2  # noqa: E402
from pir2 import gr00t as pg  # noqa: E402

from n17_reference import ActionHead, ref_velocity  # noqa: E402

H = 12
D_VL = 24
T = 10
A_MAX = 20
S_MAX = 48


def config():
    return {
        "model_type": "Gr00tN1d7",
        "action_horizon": 16,
        "add_pos_embed": True,
        "attend_text_every_n_blocks": 2,
        "backbone_embedding_dim": D_VL,
        "diffusion_model_cfg": {
            "num_layers": 4, "num_attention_heads": 2, "attention_head_dim": 8,
            "norm_type": "ada_norm", "dropout": 0.2, "final_dropout": True,
            "output_dim": 16, "interleave_self_attention": True, "positional_embeddings": None,
        },
        "hidden_size": 16,
        "input_embedding_dim": 16,
        "max_action_dim": A_MAX,
        "max_num_embodiments": 12,
        "max_seq_len": 16,
        "max_state_dim": S_MAX,
        "num_inference_timesteps": 4,
        "num_timestep_buckets": 1000,
        "state_history_length": 1,
        "use_alternate_vl_dit": True,
        "use_vlln": True,
    }


def make_head(seed=0):
    torch.manual_seed(seed)
    head = ActionHead(config())
    with torch.no_grad():  # non-trivial modulation and biases
        for p in head.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return head.eval()


def inputs(b=2, seed=1):
    g = torch.Generator().manual_seed(seed)
    image = torch.zeros(b, T, dtype=torch.bool)
    image[:, 3:8] = True
    attn = torch.ones(b, T, dtype=torch.bool)
    attn[:, -1] = False
    bo = {"backbone_features": torch.randn(b, T, D_VL, generator=g), "image_mask": image,
          "backbone_attention_mask": attn}
    ai = {"state": torch.randn(b, 1, S_MAX, generator=g), "embodiment_id": torch.tensor([10] * b)}
    x = torch.randn(b, H, A_MAX, generator=g)
    return bo, ai, x


def test_converted_head_computes_what_the_shared_head_computed():
    base = make_head()
    bo, ai, x = inputs()
    t = 437
    want = ref_velocity(base, bo, ai["state"], ai["embodiment_id"], x, torch.tensor([t, t]))
    conv = pg.to_per_position(copy.deepcopy(base), H, state_timestep=t).eval()
    tau = np.full((2, H), (t + 0.5) / 1000.0, np.float32)
    got = pg.velocity(conv, bo, ai, x, tau)
    assert torch.allclose(got, want, atol=1e-6, rtol=0), (got - want).abs().max()
    # GR00T's own call (a shared timestep [B]) on the converted DiT: the same numbers
    sa = torch.randn(2, 1 + H, 16)
    vl = conv.process_backbone_output(bo)
    y_shared = conv.model(sa, vl["backbone_features"], timestep=torch.tensor([t, t]),
                          image_mask=bo["image_mask"], backbone_attention_mask=bo["backbone_attention_mask"])
    y_base = base.model(sa, vl["backbone_features"], timestep=torch.tensor([t, t]),
                        image_mask=bo["image_mask"], backbone_attention_mask=bo["backbone_attention_mask"])
    assert torch.allclose(y_shared, y_base, atol=1e-6, rtol=0)


def test_state_dict_has_the_names_pir2_loads():
    conv = pg.to_per_position(make_head(), H, d_vis_max=5)
    sd = conv.state_dict()
    d = 16
    for i in range(4):
        assert tuple(sd[f"model.transformer_blocks.{i}.norm1.linear_heads.weight"].shape) == (1 + H, 2 * d, d)
        assert tuple(sd[f"model.transformer_blocks.{i}.norm1.linear_heads.bias"].shape) == (1 + H, 2 * d)
        assert f"model.transformer_blocks.{i}.norm1.linear.weight" not in sd
    assert tuple(sd["model.proj_out_1_heads.weight"].shape) == (1 + H, 2 * d, d)
    assert "model.proj_out_1.weight" not in sd
    assert tuple(sd["delay_embedding.weight"].shape) == (6, d)
    assert float(sd["delay_embedding.weight"].abs().sum()) == 0.0
    assert pg.is_per_position(conv)
    base_n = pg.parameter_count(make_head())
    mod = 4 * (2 * d * d + 2 * d) + (2 * d * d + 2 * d)
    assert pg.parameter_count(conv) == base_n + H * mod + 6 * d


def test_training_with_the_draws_specialises_the_heads():
    head = pg.to_per_position(make_head(), H, schedule=pir2.TrainSchedule.for_policy("pi_r2", {"nfe": 2, "pir2_d_max": 3}), seed=3)
    head.train()
    opt = torch.optim.Adam(head.parameters(), lr=1e-2)
    bo, ai, _ = inputs(b=4)
    ai["action"] = torch.randn(4, H, A_MAX)
    ai["action_mask"] = torch.ones(4, H, A_MAX)
    torch.manual_seed(0)
    for _ in range(3):
        out = head(bo, ai)
        assert torch.isfinite(out["loss"])
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
    w = head.model.proj_out_1_heads.weight.detach()
    assert (w[1] - w[-1]).abs().max() > 1e-4, "per-position heads did not specialise"
    w0 = head.model.transformer_blocks[0].norm1.linear_heads.weight.detach()
    assert (w0[0] - w0[5]).abs().max() > 1e-4


def test_the_head_draws_what_pir2_draws():
    sched = pir2.TrainSchedule.for_policy("pi_r2", {"nfe": 2, "pir2_d_max": 3})
    head = pg.to_per_position(make_head(), H, schedule=sched, seed=11, rank=2)
    state = pg.draw_state(head)
    want = sched.draw(4, H, pir2.Rng.derive(11, 2))
    got = head._pir2_schedule.draw(4, H, head._pir2_rng)
    np.testing.assert_array_equal(got.tau, want.tau)
    np.testing.assert_array_equal(got.mask, want.mask)
    pg.load_draw_state(head, state)  # resume: the same stream again
    again = head._pir2_schedule.draw(4, H, head._pir2_rng)
    np.testing.assert_array_equal(again.tau, want.tau)


def test_step_inputs_follow_pir2s_build():
    head = pg.to_per_position(make_head(), H)
    sched = pir2.TrainSchedule.for_policy("pi_r2_hidden", {"nfe": 2, "pir2_d_max": 3})
    d = sched.draw(16, H, 5)
    a = np.random.default_rng(0).standard_normal((16, H, A_MAX)).astype(np.float32)
    e = np.random.default_rng(1).standard_normal((16, H, A_MAX)).astype(np.float32)
    x, tau_in, target = d.build(a, e)
    step = pg.pir2_step_inputs(head, torch.from_numpy(a), d, torch.from_numpy(e))
    np.testing.assert_allclose(step["x"].numpy(), x, atol=1e-6)
    np.testing.assert_array_equal(step["tau"].numpy(), tau_in)
    np.testing.assert_array_equal(step["target"].numpy(), target)
    assert d.hidden.any()
    assert int(step["timesteps"].min()) >= 0 and int(step["timestep"][:, 0].max()) == 999


def test_bad_input_is_a_value_error():
    with pytest.raises(ValueError, match="horizon"):
        pg.to_per_position(make_head(), 0)
    with pytest.raises(ValueError, match="max_seq_len"):
        pg.to_per_position(make_head(), 40)
    with pytest.raises(ValueError, match="too short"):
        pg.to_per_position(make_head(), 4, schedule=pir2.TrainSchedule.for_policy("pi_r2", {"nfe": 2}))
    head = pg.to_per_position(make_head(), H)
    with pytest.raises(ValueError, match="already has per-position heads"):
        pg.to_per_position(head, H - 1)
    bo, ai, x = inputs()
    with pytest.raises(ValueError, match="tokens"):
        pg.velocity(head, bo, ai, x[:, :5], np.zeros((2, 5), np.float32))
    bad = x.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        pg.pir2_step_inputs(head, bad, np.zeros((2, H), np.float32), torch.zeros_like(bad))
    with pytest.raises(ValueError, match="tau has shape"):
        pg.pir2_step_inputs(head, x, np.zeros((2, H + 1), np.float32), torch.zeros_like(x))
