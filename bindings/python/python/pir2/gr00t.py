"""GR00T N1.7's action head in πR²'s per-position form, for PyTorch trainers (needs torch).

``import pir2`` needs no torch; this module does. It changes an Isaac-GR00T N1.7 action head
(``Gr00tN1d7ActionHead``, or any module with the same attribute layout) in place:

1. **Per-position modulation heads** (:func:`to_per_position`): every AdaLN modulation of the
   DiT — each block's ``norm1.linear`` and the output's ``proj_out_1`` — becomes one linear
   head per DiT token (the state token, then the ``H`` action tokens), each a copy of the
   shared layer. The converted head computes exactly what it computed before for any
   timesteps, and the heads specialise when it is fine-tuned. Tensor names follow pir2's
   GR00T loader: ``model.transformer_blocks.{i}.norm1.linear_heads.{weight,bias}`` and
   ``model.proj_out_1_heads.{weight,bias}`` with ``weight [1 + H, out, in]`` and
   ``bias [1 + H, out]`` replace ``norm1.linear.*`` and ``proj_out_1.*``; an optional
   zero-initialised ``delay_embedding.weight [d_vis_max + 1, D_in]`` (the slow channel's age
   ``d_vis``) is added to every action token.
2. **Per-token timesteps**: the DiT takes ``timestep [B]`` (GR00T's shared timestep) or
   ``[B, 1 + H]`` (one per token); every AdaLN and the output modulation read their token's own
   embedding.
3. **The πR² training step**: the converted head's ``forward(backbone_output,
   action_input)`` (the call Isaac-GR00T's trainer makes) draws the per-position flow times
   and loss masks from a :class:`pir2.TrainSchedule` — the same draws, bit for bit, as pir2's
   Rust trainer for a seed — instead of GR00T's one Beta time per sample, and returns
   ``{"loss": ...}`` as GR00T's head does. :func:`pir2_step_inputs` exposes the same
   construction for a trainer of your own.

Convention (pir2's and GR00T's): ``τ = 0`` is noise, ``τ = 1`` is clean,
``x = (1 − τ)·ε + τ·a``, velocity target ``a − ε``, discrete timestep
``min(⌊τ·buckets⌋, buckets − 1)`` per position; the state token's timestep is
``state_timestep`` (pir2's default: the last bucket, ``buckets − 1``).

The behaviour reproduced is that of Isaac-GR00T's ``gr00t/model/modules/dit.py`` (``DiT``,
``AlternateVLDiT``, ``AdaLayerNorm``, the ``kv_cache`` of its inference path) and
``gr00t/model/gr00t_n1d7/gr00t_n1d7.py`` (``Gr00tN1d7ActionHead.forward``) as published on
GitHub (NVIDIA/Isaac-GR00T, 2026); no code of theirs is used. The package's
``tests/test_gr00t_isaac.py`` runs the conversion on those real classes, given a checkout
(``PIR2_ISAAC_GR00T``; last run against commit 2ea60d6d388d08fcc734dd339c6e183fdab5309c):
a uniform ``τ`` gives the real DiT's velocity within 1e-6. What is bit-identical to pir2's
Rust trainer: the schedule draws (``τ``, mask, delay) for a seed. What is not: the noise ``ε``
(torch's generator), the network's floating-point evaluation order, batching and the
optimiser.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np

try:
    import torch
    from torch import nn
    import torch.nn.functional as F
except ImportError as e:  # pragma: no cover - exercised only without torch
    raise ImportError(
        "pir2.gr00t needs PyTorch (pip install torch); the rest of pir2 does not"
    ) from e

from ._pir2 import HIDDEN_FRONT_TAU, Rng, TrainSchedule

__all__ = [
    "PerPositionLinear",
    "PerPositionAdaLayerNorm",
    "to_per_position",
    "timestep_buckets",
    "pir2_step_inputs",
    "is_per_position",
    "velocity",
    "default_schedule",
    "parameter_count",
    "draw_state",
    "load_draw_state",
]


class PerPositionLinear(nn.Module):
    """One linear layer per token: ``y[..., p, :] = x[..., p, :] @ weight[p].T + bias[p]``.

    ``weight [n, out, in]``, ``bias [n, out]``. An input of shape ``[..., in]`` (one vector
    for every token, e.g. GR00T's shared timestep embedding) is applied to every head and
    gives ``[..., n, out]``.
    """

    def __init__(self, n: int, in_features: int, out_features: int, *, device=None, dtype=None):
        super().__init__()
        if n < 1 or in_features < 1 or out_features < 1:
            raise ValueError(
                f"PerPositionLinear needs n, in_features, out_features >= 1, got {n}, "
                f"{in_features}, {out_features}"
            )
        self.n, self.in_features, self.out_features = n, in_features, out_features
        self.weight = nn.Parameter(torch.empty(n, out_features, in_features, device=device, dtype=dtype))
        self.bias = nn.Parameter(torch.empty(n, out_features, device=device, dtype=dtype))

    @classmethod
    def from_linear(cls, linear: nn.Linear, n: int) -> "PerPositionLinear":
        """``n`` copies of ``linear`` (same device, dtype and ``requires_grad``)."""
        if not isinstance(linear, nn.Linear):
            raise TypeError(f"expected an nn.Linear to copy, got {type(linear).__name__}")
        if linear.bias is None:
            raise ValueError("the shared modulation layer has no bias; GR00T's has one")
        w = linear.weight
        m = cls(n, linear.in_features, linear.out_features, device=w.device, dtype=w.dtype)
        with torch.no_grad():
            m.weight.copy_(w.detach().unsqueeze(0).expand(n, -1, -1))
            m.bias.copy_(linear.bias.detach().unsqueeze(0).expand(n, -1))
        m.weight.requires_grad_(w.requires_grad)
        m.bias.requires_grad_(linear.bias.requires_grad)
        return m

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != self.in_features:
            raise ValueError(
                f"PerPositionLinear: input width {x.shape[-1]}, the heads take {self.in_features}"
            )
        if x.dim() >= 2 and x.shape[-2] == self.n and x.dim() >= 3:
            return torch.einsum("...ni,noi->...no", x, self.weight) + self.bias
        if x.dim() >= 3:
            raise ValueError(
                f"PerPositionLinear: {x.shape[-2]} tokens, the layer has {self.n} heads "
                "(1 state token + H action tokens)"
            )
        # one vector per sample: every head applied to it
        return torch.einsum("...i,noi->...no", x, self.weight) + self.bias

    def extra_repr(self) -> str:
        return f"n={self.n}, in_features={self.in_features}, out_features={self.out_features}"


class PerPositionAdaLayerNorm(nn.Module):
    """GR00T's ``AdaLayerNorm`` with one modulation head per token.

    ``LN(x)·(1 + scale) + shift`` with ``[scale, shift] = linear_heads(silu(temb))`` per token
    (``scale`` first, as GR00T's blocks). ``temb`` is ``[B, T, D]`` (per token) or ``[B, D]``
    (shared: every token's head applied to it).
    """

    def __init__(self, shared: nn.Module, n: int):
        super().__init__()
        if not isinstance(getattr(shared, "linear", None), nn.Linear) or not isinstance(
            getattr(shared, "norm", None), nn.LayerNorm
        ):
            raise TypeError(
                "expected GR00T's AdaLayerNorm (attributes `linear: nn.Linear` and `norm: "
                f"nn.LayerNorm`), got {type(shared).__name__}"
            )
        self.silu = nn.SiLU()
        self.norm = shared.norm
        self.linear_heads = PerPositionLinear.from_linear(shared.linear, n)

    def forward(self, x: torch.Tensor, temb: Optional[torch.Tensor] = None) -> torch.Tensor:
        if temb is None:
            raise ValueError("PerPositionAdaLayerNorm needs the timestep embedding `temb`")
        m = self.linear_heads(self.silu(temb))
        if m.shape[-2] != x.shape[-2]:
            raise ValueError(
                f"PerPositionAdaLayerNorm: {x.shape[-2]} tokens, {m.shape[-2]} modulation heads"
            )
        scale, shift = m.chunk(2, dim=-1)
        return self.norm(x) * (1 + scale) + shift


def is_per_position(action_head: nn.Module) -> bool:
    """Whether :func:`to_per_position` has converted this head."""
    return isinstance(getattr(action_head.model, "proj_out_1_heads", None), PerPositionLinear)


def _token_embedding(dit: nn.Module, timestep: torch.Tensor, tokens: int) -> torch.Tensor:
    """The DiT's timestep embedding per token ``[B, tokens, D]`` from ``[B]`` or ``[B, tokens]``."""
    if timestep is None:
        raise ValueError("the per-position DiT needs `timestep` ([B] or [B, 1 + H])")
    if timestep.dim() == 1:
        timestep = timestep[:, None].expand(-1, tokens)
    elif timestep.dim() != 2 or timestep.shape[1] != tokens:
        raise ValueError(
            f"timestep of shape {tuple(timestep.shape)}: expected [B] or [B, {tokens}] "
            "(one per DiT token: the state token, then the action tokens)"
        )
    b = timestep.shape[0]
    # GR00T's timestep encoder is per element; run it on the flattened timesteps.
    emb = dit.timestep_encoder(timestep.reshape(-1))
    return emb.reshape(b, tokens, -1)


class _PerPositionDiT:
    """The forward of GR00T's ``DiT`` / ``AlternateVLDiT`` with per-token modulation."""

    def forward(
        self,
        hidden_states: torch.Tensor,
        encoder_hidden_states: torch.Tensor,
        timestep: Optional[torch.Tensor] = None,
        encoder_attention_mask: Optional[torch.Tensor] = None,
        return_all_hidden_states: bool = False,
        image_mask: Optional[torch.Tensor] = None,
        backbone_attention_mask: Optional[torch.Tensor] = None,
        kv_cache: Optional[dict] = None,
    ):
        temb = _token_embedding(self, timestep, hidden_states.shape[1])
        hidden_states = hidden_states.contiguous()
        encoder_hidden_states = encoder_hidden_states.contiguous()
        cfg = getattr(self, "config", None)
        interleave = bool(getattr(cfg, "interleave_self_attention", False))
        every = getattr(self, "attend_text_every_n_blocks", None)
        alternate = every is not None
        if alternate:
            if image_mask is None or backbone_attention_mask is None:
                raise ValueError("AlternateVLDiT needs image_mask and backbone_attention_mask")
            image_attention = image_mask & backbone_attention_mask
            text_attention = (~image_mask) & backbone_attention_mask
        all_hidden = [hidden_states]
        for idx, block in enumerate(self.transformer_blocks):
            if idx % 2 == 1 and (interleave or alternate):
                hidden_states = block(
                    hidden_states,
                    attention_mask=None,
                    encoder_hidden_states=None,
                    encoder_attention_mask=None,
                    temb=temb,
                )
            else:
                mask = None
                if alternate:
                    mask = text_attention if idx % (2 * every) == 0 else image_attention
                extra = {"kv_cache": kv_cache, "cache_key": idx} if kv_cache is not None else {}
                hidden_states = block(
                    hidden_states,
                    attention_mask=None,
                    encoder_hidden_states=encoder_hidden_states,
                    encoder_attention_mask=mask,
                    temb=temb,
                    **extra,
                )
            all_hidden.append(hidden_states)
        shift, scale = self.proj_out_1_heads(F.silu(temb)).chunk(2, dim=-1)
        hidden_states = self.norm_out(hidden_states) * (1 + scale) + shift
        out = self.proj_out_2(hidden_states)
        return (out, all_hidden) if return_all_hidden_states else out


class _PiR2ActionHead:
    """``forward`` of the action head replaced by the πR² training step (see the module docs)."""

    def forward(self, backbone_output: Mapping[str, Any], action_input: Mapping[str, Any]):
        if hasattr(self, "set_frozen_modules_to_eval_mode"):
            self.set_frozen_modules_to_eval_mode()
        if hasattr(self, "process_backbone_output"):
            backbone_output = self.process_backbone_output(backbone_output)
        actions = _get(action_input, "action")
        b, h = actions.shape[0], actions.shape[1]
        draw = self._pir2_schedule.draw(b, h, self._pir2_rng)
        noise = torch.randn(actions.shape, device=actions.device, dtype=actions.dtype)
        d_vis = _opt(action_input, "d_vis")
        step = pir2_step_inputs(self, actions, draw, noise)
        pred = _velocity(self, backbone_output, action_input, step["x"], step["tau"], d_vis)
        loss_mask = torch.as_tensor(draw.mask, device=actions.device, dtype=actions.dtype)[..., None]
        action_mask = _opt(action_input, "action_mask")
        m = loss_mask if action_mask is None else action_mask * loss_mask
        err = F.mse_loss(pred, step["target"], reduction="none") * m
        loss = err.sum() / (m.expand_as(err).sum() + 1e-6)
        return {"loss": loss, "action_loss": err, "action_mask": m, "tau": step["tau"]}


def _get(d: Mapping[str, Any], key: str):
    try:
        return d[key]
    except (KeyError, TypeError):
        v = getattr(d, key, None)
        if v is None:
            raise KeyError(f"the action input has no `{key}`") from None
        return v


def _opt(d: Mapping[str, Any], key: str):
    try:
        return d[key]
    except (KeyError, TypeError):
        return getattr(d, key, None)


def timestep_buckets(tau: torch.Tensor, buckets: int) -> torch.Tensor:
    """GR00T's discrete timesteps per position: ``min(⌊clamp(τ, 0, 1)·buckets⌋, buckets − 1)``."""
    t = torch.floor(tau.clamp(0.0, 1.0).to(torch.float32) * buckets).long()
    return t.clamp(max=buckets - 1)


def pir2_step_inputs(action_head: nn.Module, actions: torch.Tensor, draw, noise: torch.Tensor):
    """The πR² model input of one batch: ``x = (1 − τ)·ε + τ·a``, the velocity target ``a − ε``,
    the model's per-position ``tau`` and the timesteps (per action position ``[B, H]``, per DiT
    token ``[B, 1 + H]``), as pir2's ``Draw::build`` makes them.

    ``actions [B, H, A_max]`` (GR00T's padded, normalised actions), ``draw`` a
    :class:`pir2.Draws` of ``B`` samples (or a ``[B, H]`` array of flow times), ``noise`` like
    ``actions``. On a hidden front (policy ``pi_r2_hidden``) the front's input is zero and its
    ``tau`` is ``HIDDEN_FRONT_TAU`` (timestep 0), as in pir2's trainer.
    """
    if actions.dim() != 3:
        raise ValueError(f"actions must be [B, H, A], got shape {tuple(actions.shape)}")
    hidden = None
    if hasattr(draw, "tau") and hasattr(draw, "hidden"):
        tau = torch.as_tensor(np.asarray(draw.tau))
        h = tau.shape[1] if tau.dim() == 2 else 0
        front = np.arange(h)[None, :] < np.asarray(draw.delay)[:, None]
        hidden = torch.as_tensor(np.asarray(draw.hidden)[:, None] & front, device=actions.device)
    else:
        tau = torch.as_tensor(np.asarray(draw) if not torch.is_tensor(draw) else draw)
    tau = tau.to(device=actions.device, dtype=actions.dtype)
    if tuple(tau.shape) != tuple(actions.shape[:2]):
        raise ValueError(
            f"tau has shape {tuple(tau.shape)}, the actions {tuple(actions.shape)}: expected [B, H]"
        )
    if noise.shape != actions.shape:
        raise ValueError(f"noise has shape {tuple(noise.shape)}, the actions {tuple(actions.shape)}")
    if not torch.isfinite(tau).all() or not torch.isfinite(actions).all():
        raise ValueError("non-finite actions or flow times")
    buckets = int(action_head._pir2_buckets)
    t_act = timestep_buckets(tau, buckets)
    t_state = torch.full((actions.shape[0], 1), int(action_head._pir2_state_timestep), dtype=torch.long, device=actions.device)
    t3 = tau[..., None]
    x = (1 - t3) * noise + t3 * actions
    if hidden is not None and bool(hidden.any()):
        x = x.masked_fill(hidden[..., None], 0.0)
        tau = tau.masked_fill(hidden, HIDDEN_FRONT_TAU)
        t_act = timestep_buckets(tau, buckets)
    return {
        "x": x,
        "target": actions - noise,
        "tau": tau,
        "timesteps": t_act,
        "timestep": torch.cat([t_state, t_act], dim=1),
    }


def _velocity(head, backbone_output, action_input, x, tau, d_vis=None):
    """One NFE of the per-position head on noisy actions ``x [B, H, A_max]`` at ``tau [B, H]``
    (``backbone_output`` already through ``process_backbone_output``)."""
    b, h, _ = x.shape
    emb = _get(action_input, "embodiment_id")
    state = _get(action_input, "state")
    state = state.reshape(state.shape[0], 1, -1)
    s = head.state_encoder(state, emb)
    if head.training and getattr(head, "state_dropout_prob", 0.0) > 0:
        keep = (torch.rand(s.shape[0], device=s.device) >= head.state_dropout_prob).to(s.dtype)
        s = s * keep[:, None, None]
    t_act = timestep_buckets(tau, int(head._pir2_buckets))
    # The action encoder is token-wise: one token per row, so it needs only GR00T's
    # one-timestep-per-sample interface.
    a = head.action_encoder(
        x.reshape(b * h, 1, x.shape[-1]), t_act.reshape(b * h), emb.repeat_interleave(h)
    ).reshape(b, h, -1)
    cfg = getattr(head, "config", None)
    if getattr(cfg, "add_pos_embed", hasattr(head, "position_embedding")) and hasattr(head, "position_embedding"):
        pos = torch.arange(h, device=x.device)
        a = a + head.position_embedding(pos).unsqueeze(0)
    table = getattr(head, "delay_embedding", None)
    if table is not None:
        if d_vis is None:
            d_vis = torch.zeros(b, dtype=torch.long, device=x.device)
        d_vis = torch.as_tensor(d_vis, device=x.device).long().clamp(0, table.num_embeddings - 1)
        a = a + table(d_vis)[:, None, :]
    sa = torch.cat([s, a], dim=1)
    t_state = torch.full((b, 1), int(head._pir2_state_timestep), dtype=torch.long, device=x.device)
    timestep = torch.cat([t_state, t_act], dim=1)
    vl = _get(backbone_output, "backbone_features")
    kw = dict(
        hidden_states=sa,
        encoder_hidden_states=vl,
        encoder_attention_mask=_opt(backbone_output, "backbone_attention_mask"),
        timestep=timestep,
        return_all_hidden_states=False,
    )
    if getattr(head.model, "attend_text_every_n_blocks", None) is not None:
        kw["image_mask"] = _get(backbone_output, "image_mask")
        kw["backbone_attention_mask"] = _get(backbone_output, "backbone_attention_mask")
    y = head.model(**kw)
    pred = head.action_decoder(y, emb)
    return pred[:, -h:]


def velocity(
    action_head: nn.Module,
    backbone_output,
    action_input,
    x,
    tau,
    d_vis=None,
    *,
    backbone_processed: bool = False,
):
    """One NFE of a converted head: the velocity ``[B, H, A_max]`` at noisy actions ``x`` and
    per-position flow times ``tau [B, H]``, as pir2's runtime computes it (state token at
    ``state_timestep``; ``d_vis`` selects the delay embedding row). ``backbone_output`` holds
    ``backbone_features`` (and ``image_mask``, ``backbone_attention_mask``); ``action_input``
    ``state`` (normalised, padded) and ``embodiment_id``. The features are the backbone's
    output, passed through the head's ``vlln`` and VL self-attention here, unless
    ``backbone_processed`` (e.g. ``vl_embs`` of ``pir2 run --record-nfe``, which the DiT takes
    after them)."""
    if not is_per_position(action_head):
        raise ValueError("velocity() needs a head converted by pir2.gr00t.to_per_position")
    bo = dict(backbone_output.items()) if hasattr(backbone_output, "items") else backbone_output
    if not backbone_processed and hasattr(action_head, "process_backbone_output"):
        bo = action_head.process_backbone_output(bo)
    tau = torch.as_tensor(np.asarray(tau) if not torch.is_tensor(tau) else tau).to(x.device, x.dtype)
    return _velocity(action_head, bo, action_input, x, tau, d_vis)


_RETYPED: dict = {}


def _retype(obj: nn.Module, mixin: type) -> None:
    """Give ``obj`` the methods of ``mixin`` (before its own class's) without touching its
    parameters or their names."""
    cls = type(obj)
    if issubclass(cls, mixin):
        return
    key = (cls, mixin)
    if key not in _RETYPED:
        _RETYPED[key] = type(f"PerPosition{cls.__name__}", (mixin, cls), {"__module__": __name__})
    obj.__class__ = _RETYPED[key]


def to_per_position(
    action_head: nn.Module,
    horizon: int,
    *,
    schedule: Optional[TrainSchedule] = None,
    seed: int = 0,
    rank: Optional[int] = None,
    d_vis_max: Optional[int] = None,
    state_timestep: Optional[int] = None,
) -> nn.Module:
    """Convert a GR00T N1.7 action head to πR²'s per-position form, in place; returns it.

    - ``horizon``: the chunk length ``H`` the head is fine-tuned and deployed with (the length
      of the action ``delta_indices``; ``1 + H`` heads per layer). At most the config's
      ``max_seq_len`` when the head adds position embeddings.
    - ``schedule``: the πR² training draws (default :func:`default_schedule`: πR² with 2 NFEs
      and the largest delay range that fits ``H``, the policy ``pir2 gr00t import`` gives a
      per-position head); validated for ``H``.
    - ``seed`` / ``rank``: the draws come from ``Rng.derive(seed, rank)`` (``rank`` defaults to
      ``torch.distributed``'s rank, 0 without it), so every data-parallel rank draws its own
      stream and a run is reproducible per rank.
    - ``d_vis_max``: add a zero-initialised delay table ``delay_embedding`` with
      ``d_vis_max + 1`` rows (pir2's default is 5), unless the head has one. ``None``: none added.
    - ``state_timestep``: the state token's timestep (default ``num_timestep_buckets − 1``,
      pir2's default; must equal the deployed embodiment's ``state_token_timestep``).

    The converted head computes exactly what the original computed (each head a copy of the
    shared layer; the delay table zero), and its state dict holds the per-position tensors pir2's
    loader reads. Converting twice is an error unless the head count matches.
    """
    if not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"horizon must be a positive int, got {horizon!r}")
    n = horizon + 1
    dit = getattr(action_head, "model", None)
    blocks = getattr(dit, "transformer_blocks", None)
    if dit is None or blocks is None:
        raise TypeError("expected GR00T N1.7's action head: `model` (the DiT) with `transformer_blocks`")
    cfg = getattr(action_head, "config", None)
    max_seq = getattr(cfg, "max_seq_len", None)
    if getattr(cfg, "add_pos_embed", False) and max_seq is not None and horizon > max_seq:
        raise ValueError(f"horizon {horizon} exceeds the position table (max_seq_len = {max_seq})")
    if is_per_position(action_head):
        have = dit.proj_out_1_heads.n
        if have != n:
            raise ValueError(f"the head already has per-position heads for {have} tokens, not 1 + {horizon}")
    else:
        for block in blocks:
            norm1 = getattr(block, "norm1", None)
            if isinstance(getattr(norm1, "linear", None), nn.Linear):
                block.norm1 = PerPositionAdaLayerNorm(norm1, n)
        if not isinstance(getattr(dit, "proj_out_1", None), nn.Linear):
            raise TypeError("expected the DiT's output modulation `proj_out_1: nn.Linear`")
        dit.proj_out_1_heads = PerPositionLinear.from_linear(dit.proj_out_1, n)
        del dit.proj_out_1
        _retype(dit, _PerPositionDiT)
    if d_vis_max is not None and getattr(action_head, "delay_embedding", None) is None:
        if d_vis_max < 0:
            raise ValueError(f"d_vis_max must be >= 0, got {d_vis_max}")
        ref = dit.proj_out_1_heads.weight
        width = _token_width(action_head)
        table = nn.Embedding(d_vis_max + 1, width, device=ref.device, dtype=ref.dtype)
        nn.init.zeros_(table.weight)
        action_head.delay_embedding = table
    buckets = int(getattr(cfg, "num_timestep_buckets", 1000) or 1000)
    action_head._pir2_buckets = buckets
    st = buckets - 1 if state_timestep is None else int(state_timestep)
    if not 0 <= st < buckets:
        raise ValueError(f"state_timestep {st} is outside [0, {buckets})")
    action_head._pir2_state_timestep = st
    action_head._pir2_horizon = horizon
    if schedule is None:
        schedule = default_schedule(horizon)
    schedule.validate(horizon)
    action_head._pir2_schedule = schedule
    if rank is None:
        rank = 0
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            rank = torch.distributed.get_rank()
    action_head._pir2_rng = Rng.derive(seed, rank)
    _retype(action_head, _PiR2ActionHead)
    return action_head


def default_schedule(horizon: int, nfe: int = 2) -> TrainSchedule:
    """πR² with ``nfe`` NFEs per action and the largest ``d_max ≤ min(5, H − 1)`` the fresh
    staircase takes at ``H`` — the policy and delay range ``pir2 gr00t import`` gives a head
    with per-position heads (its ``[policy]`` and ``d_max``)."""
    last = None
    for d in range(min(5, horizon - 1), 0, -1):
        s = TrainSchedule.for_policy("pi_r2", {"nfe": nfe, "pir2_d_max": d})
        try:
            s.validate(horizon)
            return s
        except ValueError as e:
            last = e
    raise ValueError(f"no πR² delay range fits H = {horizon} with nfe = {nfe}: {last}")


def _token_width(action_head: nn.Module) -> int:
    """``D_in``, the width of the state and action tokens."""
    cfg = getattr(action_head, "config", None)
    w = getattr(cfg, "input_embedding_dim", None)
    if w is None:
        w = getattr(action_head, "input_embedding_dim", None)
    if w is None:
        raise ValueError("cannot tell the token width D_in (config.input_embedding_dim)")
    return int(w)


def parameter_count(action_head: nn.Module) -> int:
    """Parameters of the head (after conversion: ``(1 + H)×`` the modulation layers')."""
    return sum(p.numel() for p in action_head.parameters())


def draw_state(action_head: nn.Module) -> list:
    """The state of the head's draw generator (save it with a training checkpoint)."""
    return list(action_head._pir2_rng.state)


def load_draw_state(action_head: nn.Module, state) -> None:
    """Resume the head's draws from :func:`draw_state`'s value."""
    action_head._pir2_rng = Rng.from_state(list(state))

