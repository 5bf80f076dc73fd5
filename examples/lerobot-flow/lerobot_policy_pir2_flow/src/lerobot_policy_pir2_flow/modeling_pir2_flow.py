"""The ``pir2_flow`` LeRobot policy: a πR² flow MLP trained with pir2's per-position draws."""

from __future__ import annotations

from collections import deque

import numpy as np
import pir2
import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.utils.constants import ACTION
from torch import Tensor

from .configuration_pir2_flow import Pir2FlowConfig
from .flow import FlowMLP, compute_stats, flow_loss, load_episodes

#: Stream of ``pir2.Rng.derive(seed, ·)`` drawing the slow-feature ages and the noise ε
#: (the schedule draws use ``pir2.Rng(seed)`` itself, as ``train.py`` does).
SAMPLE_STREAM = 1


def _state_tensor(rng: pir2.Rng) -> Tensor:
    """A generator's four u64 words as an int64 tensor (same bits), to save with the weights."""
    return torch.from_numpy(np.asarray(rng.state, np.uint64).view(np.int64).copy())


def _rng(state: Tensor) -> pir2.Rng:
    return pir2.Rng.from_state(state.detach().cpu().numpy().view(np.uint64).tolist())


def dataset_stats_pir2(repo_id: str, root, config: Pir2FlowConfig) -> dict:
    """pir2's normalisation statistics of the dataset's features named by ``config``."""
    _, episodes = load_episodes(root, config.fast_features, config.slow_features, ACTION,
                                repo_id=repo_id)
    return compute_stats(episodes)


class Pir2FlowPolicy(PreTrainedPolicy):
    """πR² flow policy for LeRobot (see :class:`Pir2FlowConfig`).

    Training (:meth:`forward`) is pir2's: for a batch of windows LeRobot cut from the
    dataset (``delta_timestamps`` from the config), the schedule draws come from
    ``pir2.TrainSchedule.for_policy`` and the loss is pir2's masked flow loss. The draw
    generators' states are buffers, saved with the weights, so a resumed run continues the
    sequence. Inference on the LeRobot side (:meth:`select_action`) is plain synchronous flow
    sampling; pir2's real-time runtime runs the exported graph (``lerobot_policy_pir2_flow.export``).
    """

    config_class = Pir2FlowConfig
    name = "pir2_flow"

    def __init__(self, config: Pir2FlowConfig, dataset_stats=None, dataset_meta=None, **kwargs):
        """``dataset_meta`` (a ``LeRobotDatasetMetadata``, as ``make_policy`` passes it) gives
        the dataset whose frames set pir2's observation statistics; without it (or when
        ``config.pretrained_path`` is set) they stay unset until a saved state is loaded."""
        super().__init__(config)
        config.validate_features()
        self.config = config
        stats = None
        if dataset_meta is not None and not config.pretrained_path:
            stats = dataset_stats_pir2(dataset_meta.repo_id, dataset_meta.root, config)
        self.model = FlowMLP(stats, config.horizon, config.action_dim, config.n_obs_steps,
                             config.fast_dim, config.slow_dim, config.d_vis_max, config.width,
                             config.depth, config.tau_freqs)
        self.register_buffer("draw_rng_state", _state_tensor(pir2.Rng(config.seed)))
        self.register_buffer("sample_rng_state",
                             _state_tensor(pir2.Rng.derive(config.seed, SAMPLE_STREAM)))
        self._schedule = config.train_schedule()
        self.reset()

    def get_optim_params(self):
        return self.model.parameters()

    def reset(self):
        """Clear the observation and action queues and reseed the sampling noise."""
        n = self.config.n_obs_steps
        self._queues = {k: deque(maxlen=n) for k in self.config.fast_features}
        self._queues.update({k: deque(maxlen=1) for k in self.config.slow_features})
        self._queues[ACTION] = deque(maxlen=self.config.n_action_steps)
        self._noise = torch.Generator().manual_seed(self.config.seed)

    # -- inputs ------------------------------------------------------------------------------

    def _require_stats(self):
        if not self.model.has_stats():
            raise RuntimeError(
                "pir2_flow: the policy has no observation statistics: build it from a dataset "
                "(make_policy with its metadata) or load a trained one (from_pretrained)")

    def _feature(self, batch, key, frames, what):
        """``batch[key]`` as [B, T, dim] (T >= frames), checked; [B, dim] is read as T = 1."""
        if key not in batch:
            raise ValueError(f"pir2_flow: the batch has no {what} {key!r} "
                             f"(it has {', '.join(sorted(map(str, batch)))})")
        t = batch[key]
        if not isinstance(t, Tensor):
            raise ValueError(f"pir2_flow: batch[{key!r}] must be a tensor, got {type(t).__name__}")
        dim = self.config.input_features[key].shape[0]
        if t.ndim == 2:
            t = t.unsqueeze(1)
        if t.ndim != 3 or t.shape[2] != dim or t.shape[1] < frames:
            raise ValueError(f"pir2_flow: batch[{key!r}] has shape {tuple(t.shape)}, expected "
                             f"[B, T>={frames}, {dim}] (or [B, {dim}] for the current frame only)")
        if not torch.isfinite(t).all():
            raise ValueError(f"pir2_flow: batch[{key!r}] holds NaN or infinite values")
        return t.float()

    def _observations(self, batch, frames):
        """Fast history [B, n_obs, F] and slow window [B, T, S] (T = ``frames``), with the
        history clamped at the window's start (frames before it repeat its first one)."""
        n = self.config.n_obs_steps

        def last(t, k):  # the last k frames, the first one repeated when fewer
            if t.shape[1] < k:
                t = torch.cat([t[:, :1].expand(-1, k - t.shape[1], -1), t], 1)
            return t[:, -k:]

        fast = torch.cat([last(self._feature(batch, k, 1, "fast feature"), n)
                          for k in self.config.fast_features], -1)
        if self.config.slow_features:
            slow = torch.cat([last(self._feature(batch, k, 1, "slow feature"), frames)
                              for k in self.config.slow_features], -1)
        else:
            slow = fast.new_zeros(fast.shape[0], frames, 0)
        return fast, slow

    # -- training ----------------------------------------------------------------------------

    def forward(self, batch: dict[str, Tensor], reduction: str = "mean") -> tuple[Tensor, dict]:
        """pir2's masked flow loss on a training batch.

        ``batch`` holds every fast and slow feature as a window ``[B, W, dim]`` (W =
        ``config.obs_window``, the current frame last, as LeRobot loads it with the config's
        ``observation_delta_indices``) and ``action [B, H, A]`` in normalised units. Per sample:
        the fast history is the window's last ``n_obs_steps`` frames, the slow-feature age
        ``d_vis`` is drawn uniformly in ``0..=d_vis_max`` and the slow features are taken
        ``d_vis`` frames back; ε ~ N(0, 1). Ages and ε come from ``pir2.Rng.derive(seed, 1)``,
        the schedule draws from ``pir2.Rng(seed)``; both generators advance with each call.
        """
        if reduction != "mean":
            raise ValueError(f"pir2_flow: forward supports reduction='mean' only, got {reduction!r}")
        self._require_stats()
        cfg = self.config
        w = cfg.obs_window
        for key in (*cfg.fast_features, *cfg.slow_features):
            t = batch.get(key)
            if isinstance(t, Tensor) and (t.ndim != 3 or t.shape[1] != w):
                raise ValueError(
                    f"pir2_flow: batch[{key!r}] has shape {tuple(t.shape)}, expected a window "
                    f"[B, {w}, dim] (load the dataset with this config's delta_timestamps)")
        fast, slow_window = self._observations(batch, w)
        if ACTION not in batch:
            raise ValueError(f"pir2_flow: the training batch has no {ACTION!r}")
        act = batch[ACTION]
        b, h, a = fast.shape[0], cfg.horizon, cfg.action_dim
        if tuple(act.shape) != (b, h, a):
            raise ValueError(f"pir2_flow: batch[{ACTION!r}] has shape {tuple(act.shape)}, "
                             f"expected [{b}, {h}, {a}]")
        if not torch.isfinite(act).all():
            raise ValueError(f"pir2_flow: batch[{ACTION!r}] holds NaN or infinite values")

        draw_rng, sample_rng = _rng(self.draw_rng_state), _rng(self.sample_rng_state)
        d_vis = np.array([sample_rng.below(cfg.d_vis_max + 1) for _ in range(b)], np.int64)
        eps = sample_rng.normal(b * h * a).reshape(b, h, a)
        draws = self._schedule.draw(b, h, draw_rng)
        self.draw_rng_state.copy_(_state_tensor(draw_rng))
        self.sample_rng_state.copy_(_state_tensor(sample_rng))

        rows = torch.arange(b, device=slow_window.device)
        ages = torch.from_numpy(d_vis).to(slow_window.device)
        slow = slow_window[rows, w - 1 - ages]
        actions = act.detach().float().cpu().numpy()
        loss = flow_loss(self.model, draws, actions, eps, fast, slow, d_vis)
        info = {"mean_delay": float(draws.delay.mean()), "hidden_front": float(draws.hidden.mean())}
        return loss, info

    # -- LeRobot-side inference --------------------------------------------------------------

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        """A chunk ``[B, H, A]`` (normalised units) by plain synchronous flow sampling.

        Every position goes from noise (τ = 0) to clean (τ = 1) in ``num_inference_steps``
        Euler steps of the velocity model, with the current slow features (``d_vis = 0``).
        Observations: ``[B, dim]`` (current frame; the history repeats it, as at an episode
        start) or ``[B, T, dim]`` (the last frame current). This is not pir2's real-time
        runtime, which runs one denoising step per control call on a per-position schedule.
        """
        self._require_stats()
        cfg = self.config
        fast, slow = self._observations(batch, 1)
        slow = slow[:, -1]
        b, dev = fast.shape[0], next(self.model.parameters()).device
        if noise is None:
            x = torch.randn(b, cfg.horizon, cfg.action_dim, generator=self._noise).to(dev)
        else:
            if tuple(noise.shape) != (b, cfg.horizon, cfg.action_dim):
                raise ValueError(f"pir2_flow: noise has shape {tuple(noise.shape)}, expected "
                                 f"[{b}, {cfg.horizon}, {cfg.action_dim}]")
            x = noise.to(dev, torch.float32)
        d_vis = torch.zeros(b, dtype=torch.int64, device=dev)
        n = cfg.num_inference_steps
        for k in range(n):
            tau = torch.full((b, cfg.horizon), k / n, device=dev)
            x = x + self.model(x, tau, fast, slow, d_vis) / n
        return x

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], noise: Tensor | None = None) -> Tensor:
        """One action ``[B, A]`` per call: the observation history is queued (the first frame
        repeated at an episode start), a chunk is sampled when the previous one's first
        ``n_action_steps`` actions are used up."""
        for key in self._queues:
            if key != ACTION and key in batch:
                frame = batch[key]
                q = self._queues[key]
                while len(q) < q.maxlen - 1:
                    q.append(frame)
                q.append(frame)
        if not self._queues[ACTION]:
            obs = {k: torch.stack(list(q), 1) for k, q in self._queues.items()
                   if k != ACTION and q}
            chunk = self.predict_action_chunk(obs, noise=noise)
            self._queues[ACTION].extend(chunk[:, : self.config.n_action_steps].transpose(0, 1))
        return self._queues[ACTION].popleft()
