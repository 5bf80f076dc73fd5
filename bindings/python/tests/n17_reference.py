"""A GR00T N1.7-shaped action head in PyTorch, for the tests of ``pir2.gr00t`` (needs torch and
diffusers).

Isaac-GR00T is not on PyPI, so the tests build its action head here from the same building
blocks it uses (diffusers' ``Attention``, ``FeedForward``, ``Timesteps``,
``TimestepEmbedding``) with its attribute names, so that the state dict has GR00T's tensor
names (``action_head.`` stripped) and ``pir2.gr00t.to_per_position`` meets the layout it meets in
Isaac-GR00T. The behaviour follows the architecture pir2's Rust head documents
(``pir2-backends/src/gr00t/n17/mod.rs``): category-specific MLPs per embodiment, the action
encoder ``W3·silu(W2·[W1·a ; sin/cos(t)])``, the DiT's AdaLN blocks alternating cross- and
self-attention, the output modulation. GR00T's shared-timestep forward is :func:`ref_velocity`.
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import torch
from torch import nn
import torch.nn.functional as F
from diffusers.models.attention import Attention, FeedForward
from diffusers.models.embeddings import TimestepEmbedding, Timesteps


class CategorySpecificLinear(nn.Module):
    def __init__(self, n, i, o):
        super().__init__()
        self.W = nn.Parameter(0.02 * torch.randn(n, i, o))
        self.b = nn.Parameter(torch.zeros(n, o))

    def forward(self, x, cat):
        return torch.bmm(x, self.W[cat]) + self.b[cat].unsqueeze(1)


class CategorySpecificMLP(nn.Module):
    def __init__(self, n, i, h, o):
        super().__init__()
        self.layer1 = CategorySpecificLinear(n, i, h)
        self.layer2 = CategorySpecificLinear(n, h, o)

    def forward(self, x, cat):
        return self.layer2(F.relu(self.layer1(x, cat)), cat)


def sinusoid(t, width):
    """``[sin(t·ω_k), cos(t·ω_k)]``, ``ω_k = exp(−k·ln(10⁴)/(w/2))`` (GR00T's action-time encoding)."""
    half = width // 2
    k = torch.arange(half, dtype=torch.float32, device=t.device)
    w = torch.exp(-k * (math.log(10000.0) / half))
    ang = t.to(torch.float32).unsqueeze(-1) * w
    return torch.cat([torch.sin(ang), torch.cos(ang)], dim=-1)


class ActionEncoder(nn.Module):
    def __init__(self, a, d, n):
        super().__init__()
        self.hidden = d
        self.W1 = CategorySpecificLinear(n, a, d)
        self.W2 = CategorySpecificLinear(n, 2 * d, d)
        self.W3 = CategorySpecificLinear(n, d, d)

    def forward(self, actions, timesteps, cat):
        b, t, _ = actions.shape
        if timesteps.dim() == 1:
            timesteps = timesteps.unsqueeze(1).expand(-1, t)
        a = self.W1(actions, cat)
        x = torch.cat([a, sinusoid(timesteps, self.hidden).to(a.dtype)], dim=-1)
        return self.W3(F.silu(self.W2(x, cat)), cat)


class TimestepEncoder(nn.Module):
    def __init__(self, d):
        super().__init__()
        self.time_proj = Timesteps(num_channels=256, flip_sin_to_cos=True, downscale_freq_shift=1)
        self.timestep_embedder = TimestepEmbedding(in_channels=256, time_embed_dim=d)

    def forward(self, t):
        dtype = next(self.parameters()).dtype
        return self.timestep_embedder(self.time_proj(t).to(dtype))


class AdaLayerNorm(nn.Module):
    def __init__(self, d):
        super().__init__()
        self.silu = nn.SiLU()
        self.linear = nn.Linear(d, 2 * d)
        self.norm = nn.LayerNorm(d, 1e-5, False)

    def forward(self, x, temb=None):
        scale, shift = self.linear(self.silu(temb)).chunk(2, dim=1)
        return self.norm(x) * (1 + scale[:, None]) + shift[:, None]


class Block(nn.Module):
    def __init__(self, d, heads, head_dim, dropout, cross_dim, ada=True):
        super().__init__()
        self.ada = ada
        self.norm1 = AdaLayerNorm(d) if ada else nn.LayerNorm(d, eps=1e-5)
        self.attn1 = Attention(query_dim=d, heads=heads, dim_head=head_dim, dropout=dropout,
                               bias=True, cross_attention_dim=cross_dim, out_bias=True)
        self.norm3 = nn.LayerNorm(d, 1e-5, elementwise_affine=not ada)
        self.ff = FeedForward(d, dropout=dropout, activation_fn="gelu-approximate",
                              final_dropout=True, bias=True)
        self.final_dropout = nn.Dropout(dropout)

    def forward(self, h, attention_mask=None, encoder_hidden_states=None,
                encoder_attention_mask=None, temb=None):
        n = self.norm1(h, temb) if self.ada else self.norm1(h)
        a = self.attn1(n, encoder_hidden_states=encoder_hidden_states,
                       attention_mask=encoder_attention_mask if encoder_hidden_states is not None else attention_mask)
        h = self.final_dropout(a) + h
        return self.ff(self.norm3(h)) + h


class DiT(nn.Module):
    """GR00T's ``AlternateVLDiT`` (interleaved self-attention, text/image alternation)."""

    def __init__(self, c, cross_dim, every):
        super().__init__()
        d = c["num_attention_heads"] * c["attention_head_dim"]
        self.config = SimpleNamespace(interleave_self_attention=True)
        self.attend_text_every_n_blocks = every
        self.timestep_encoder = TimestepEncoder(d)
        self.transformer_blocks = nn.ModuleList(
            Block(d, c["num_attention_heads"], c["attention_head_dim"], c.get("dropout", 0.2),
                  None if i % 2 == 1 else cross_dim)
            for i in range(c["num_layers"])
        )
        self.norm_out = nn.LayerNorm(d, elementwise_affine=False, eps=1e-6)
        self.proj_out_1 = nn.Linear(d, 2 * d)
        self.proj_out_2 = nn.Linear(d, c["output_dim"])

    def forward(self, hidden_states, encoder_hidden_states, timestep=None,
                encoder_attention_mask=None, return_all_hidden_states=False,
                image_mask=None, backbone_attention_mask=None):
        temb = self.timestep_encoder(timestep)
        img = image_mask & backbone_attention_mask
        txt = (~image_mask) & backbone_attention_mask
        h = hidden_states
        for i, blk in enumerate(self.transformer_blocks):
            if i % 2 == 1:
                h = blk(h, temb=temb)
            else:
                m = txt if i % (2 * self.attend_text_every_n_blocks) == 0 else img
                h = blk(h, encoder_hidden_states=encoder_hidden_states, encoder_attention_mask=m, temb=temb)
        shift, scale = self.proj_out_1(F.silu(temb)).chunk(2, dim=1)
        h = self.norm_out(h) * (1 + scale[:, None]) + shift[:, None]
        out = self.proj_out_2(h)
        return (out, []) if return_all_hidden_states else out


class SelfAttentionTransformer(nn.Module):
    def __init__(self, c, d):
        super().__init__()
        self.transformer_blocks = nn.ModuleList(
            Block(d, c["num_attention_heads"], c["attention_head_dim"], 0.0, None, ada=False)
            for _ in range(c["num_layers"])
        )

    def forward(self, h):
        for blk in self.transformer_blocks:
            h = blk(h)
        return h


class ActionHead(nn.Module):
    """GR00T N1.7's action head from its ``config.json`` (the keys pir2 reads)."""

    def __init__(self, cfg: dict):
        super().__init__()
        c = cfg
        self.config = SimpleNamespace(**{k: v for k, v in c.items() if not isinstance(v, dict)})
        n = c["max_num_embodiments"]
        d_in, hid = c["input_embedding_dim"], c["hidden_size"]
        self.model = DiT(c["diffusion_model_cfg"], c["backbone_embedding_dim"], c.get("attend_text_every_n_blocks", 2))
        self.state_encoder = CategorySpecificMLP(n, c["max_state_dim"] * c.get("state_history_length", 1), hid, d_in)
        self.action_encoder = ActionEncoder(c["max_action_dim"], d_in, n)
        self.action_decoder = CategorySpecificMLP(n, hid, hid, c["max_action_dim"])
        self.vlln = nn.LayerNorm(c["backbone_embedding_dim"]) if c.get("use_vlln", True) else nn.Identity()
        sa = c.get("vl_self_attention_cfg")
        self.vl_self_attention = (
            SelfAttentionTransformer(sa, c["backbone_embedding_dim"]) if sa and sa.get("num_layers", 0) > 0 else nn.Identity()
        )
        if c.get("add_pos_embed", True):
            self.position_embedding = nn.Embedding(c["max_seq_len"], d_in)
        self.state_dropout_prob = 0.0

    def process_backbone_output(self, bo):
        bo = dict(bo)
        bo["backbone_features"] = self.vl_self_attention(self.vlln(bo["backbone_features"]))
        return bo

    @classmethod
    def from_checkpoint(cls, config_path, weights_path):
        from safetensors.torch import load_file

        cfg = json.loads(open(config_path).read())
        head = cls(cfg)
        sd = {k.removeprefix("action_head."): v.float() for k, v in load_file(weights_path).items()}
        extra = {k: v for k, v in sd.items() if k.startswith("delay_embedding")}
        if extra:
            w = extra["delay_embedding.weight"]
            head.delay_embedding = nn.Embedding(w.shape[0], w.shape[1])
        missing, unexpected = head.load_state_dict(sd, strict=True), None
        return head, cfg


def ref_velocity(head, bo, state, emb, x, t):
    """GR00T's one Euler-step velocity with one timestep ``t [B]`` for every token (the
    unconverted head)."""
    bo = head.process_backbone_output(bo)
    b, h, _ = x.shape
    s = head.state_encoder(state.reshape(b, 1, -1), emb)
    a = head.action_encoder(x, t, emb)
    if hasattr(head, "position_embedding"):
        a = a + head.position_embedding(torch.arange(h)).unsqueeze(0)
    if hasattr(head, "delay_embedding"):
        a = a + head.delay_embedding(torch.zeros(b, dtype=torch.long))[:, None, :]
    y = head.model(torch.cat([s, a], 1), bo["backbone_features"], timestep=t,
                   image_mask=bo["image_mask"], backbone_attention_mask=bo["backbone_attention_mask"])
    return head.action_decoder(y, emb)[:, -h:]
