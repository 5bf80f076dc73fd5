"""Configuration of the ``pir2_flow`` LeRobot policy (``--policy.type=pir2_flow``)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import pir2
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType, NormalizationMode
from lerobot.optim.optimizers import AdamWConfig
from lerobot.optim.schedulers import CosineDecayWithWarmupSchedulerConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

#: pir2's training policies (the schedule families ``pir2.TrainSchedule.for_policy`` knows).
POLICIES = ("pi_r2", "pi_r2_hidden", "pi_r2_full", "rtc", "flow", "pi_r2_zero_delay",
            "pi_r2_zero_delay_full")


@PreTrainedConfig.register_subclass("pir2_flow")
@dataclass
class Pir2FlowConfig(PreTrainedConfig):
    """A πR² flow policy: an MLP velocity model trained with pir2's per-position flow draws.

    The defaults are pir2's ball-on-plate spec (``pir2 collect ballplate`` datasets).

    Observations: ``fast_features`` (concatenated, width F) are fed as a history of
    ``n_obs_steps`` frames, encoded as ``o_t`` and its successive differences;
    ``slow_features`` (concatenated, width S; may be empty) are fed ``d_vis`` frames old, the
    age drawn uniformly in ``0..=d_vis_max`` per training sample and given to the model. Both
    come from LeRobot's ``delta_timestamps`` (``observation_delta_indices``), so every
    ``observation.*`` key is loaded over the same window of ``max(n_obs_steps, d_vis_max + 1)``
    frames. Output: a chunk of ``horizon`` actions (``action_delta_indices`` ``0..horizon``).

    Normalisation: the network normalises raw observations itself, with pir2's statistics
    of ``o_t``, of the differences and of the slow features (computed from the dataset when
    the policy is built), as the exported ONNX graph does; so ``STATE`` and ``ENV`` must map
    to ``IDENTITY``. Actions are normalised by LeRobot's processors (``ACTION``, default
    ``MEAN_STD``).

    Training draws: ``pir2.TrainSchedule.for_policy(policy, recipe)`` (``recipe``: overrides
    of pir2's default ``Recipe``, e.g. ``--policy.recipe='{"nfe": 2}'``), from generators
    seeded by ``seed`` whose state is saved with the weights, so a resumed run continues the
    same sequence.

    Inference on the LeRobot side (``select_action``): plain synchronous flow sampling, every
    position from noise to clean in ``num_inference_steps`` Euler steps, ``n_action_steps``
    actions executed per chunk. pir2's real-time runtime (one denoising step per control
    call, per-position schedule) runs the exported graph instead (``pir2 eval``).
    """

    # Spec (pir2's ball-on-plate spec by default).
    n_obs_steps: int = 2
    horizon: int = 16
    d_vis_max: int = 3
    fast_features: list[str] = field(default_factory=lambda: [OBS_STATE])
    slow_features: list[str] = field(default_factory=lambda: [OBS_ENV_STATE])

    # Training schedule: pir2 policy name and overrides of pir2's default Recipe.
    policy: str = "pi_r2"
    recipe: dict[str, Any] = field(default_factory=dict)
    seed: int = 0

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "STATE": NormalizationMode.IDENTITY,
            "ENV": NormalizationMode.IDENTITY,
            "ACTION": NormalizationMode.MEAN_STD,
        }
    )

    # Network.
    width: int = 256
    depth: int = 3
    tau_freqs: int = 4

    # LeRobot-side sampling (select_action / predict_action_chunk).
    num_inference_steps: int = 10
    n_action_steps: int = 8

    # Optimiser preset: AdamW, warm-up then cosine decay to `scheduler_decay_lr`. LeRobot
    # scales warm-up and decay to the run when `--steps` < `scheduler_decay_steps`, so the
    # defaults give a warm-up of 1/20 of any run up to 100k steps.
    optimizer_lr: float = 1e-3
    optimizer_betas: tuple[float, float] = (0.9, 0.999)
    optimizer_eps: float = 1e-8
    optimizer_weight_decay: float = 1e-4
    optimizer_grad_clip_norm: float = 1.0
    scheduler_warmup_steps: int = 5_000
    scheduler_decay_steps: int = 100_000
    scheduler_decay_lr: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        for name, low in (("n_obs_steps", 1), ("horizon", 1), ("d_vis_max", 0), ("width", 1),
                          ("depth", 1), ("tau_freqs", 0), ("num_inference_steps", 1),
                          ("n_action_steps", 1), ("scheduler_decay_steps", 1),
                          ("scheduler_warmup_steps", 0)):
            if getattr(self, name) < low:
                raise ValueError(f"pir2_flow: {name} must be >= {low}, got {getattr(self, name)}")
        if self.n_action_steps > self.horizon:
            raise ValueError(f"pir2_flow: n_action_steps ({self.n_action_steps}) must be <= "
                             f"horizon ({self.horizon})")
        if not self.fast_features:
            raise ValueError("pir2_flow: fast_features must name at least one feature")
        both = set(self.fast_features) & set(self.slow_features)
        if both:
            raise ValueError(f"pir2_flow: {sorted(both)} is in both fast_features and "
                             "slow_features")
        for ft in ("STATE", "ENV"):
            mode = NormalizationMode(self.normalization_mapping.get(ft, NormalizationMode.IDENTITY))
            if mode is not NormalizationMode.IDENTITY:
                raise ValueError(
                    f"pir2_flow: normalization_mapping[{ft!r}] must be IDENTITY, got {mode.value}: "
                    "the network normalises raw observations itself (pir2's statistics of o_t, "
                    "its differences and the slow features), as the exported graph must")
        if self.policy not in POLICIES:
            raise ValueError(f"pir2_flow: unknown policy {self.policy!r}; expected one of "
                             f"{', '.join(POLICIES)}")
        self.train_schedule()  # the recipe must parse and fit the horizon

    def train_schedule(self) -> pir2.TrainSchedule:
        """The schedule the policy is trained with (``pir2.TrainSchedule.for_policy``)."""
        recipe = self.recipe
        if not isinstance(recipe, dict):
            raise ValueError(f"pir2_flow: recipe must be a mapping of pir2 Recipe fields, got "
                             f"{recipe!r}")
        # pir2 refuses a field its Recipe does not have, naming it and listing the fields.
        try:
            schedule = pir2.TrainSchedule.for_policy(self.policy, recipe)
            schedule.validate(self.horizon)
        except ValueError as e:
            raise ValueError(f"pir2_flow: policy {self.policy!r} with recipe {self.recipe}: {e}") \
                from None
        return schedule

    @property
    def obs_window(self) -> int:
        """Frames of every observation key a sample holds (the last one is the current)."""
        slow = self.d_vis_max + 1 if self.slow_features else 1
        return max(self.n_obs_steps, slow)

    @property
    def observation_delta_indices(self) -> list[int]:
        return list(range(1 - self.obs_window, 1))

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(self.horizon))

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(
            lr=self.optimizer_lr,
            betas=self.optimizer_betas,
            eps=self.optimizer_eps,
            weight_decay=self.optimizer_weight_decay,
            grad_clip_norm=self.optimizer_grad_clip_norm,
        )

    def get_scheduler_preset(self) -> CosineDecayWithWarmupSchedulerConfig:
        return CosineDecayWithWarmupSchedulerConfig(
            num_warmup_steps=self.scheduler_warmup_steps,
            num_decay_steps=self.scheduler_decay_steps,
            peak_lr=self.optimizer_lr,
            decay_lr=self.scheduler_decay_lr,
        )

    def _width(self, key: str, table: dict, what: str) -> int:
        if key not in table:
            have = ", ".join(sorted(table)) or "none"
            raise ValueError(f"pir2_flow: {what} {key!r} is not among the policy's "
                             f"{'inputs' if what != 'action' else 'outputs'} ({have})")
        ft = table[key]
        if ft.type is FeatureType.VISUAL or len(ft.shape) != 1:
            raise ValueError(f"pir2_flow: {what} {key!r} must be a vector feature, got "
                             f"{ft.type.value} of shape {tuple(ft.shape)}")
        return int(ft.shape[0])

    def validate_features(self) -> None:
        inputs, outputs = self.input_features or {}, self.output_features or {}
        for key in self.fast_features:
            self._width(key, inputs, "fast feature")
        for key in self.slow_features:
            self._width(key, inputs, "slow feature")
        self._width(ACTION, outputs, "action")
        used = set(self.fast_features) | set(self.slow_features)
        unused = sorted(k for k in inputs if k not in used)
        if unused:
            logging.warning(
                "pir2_flow: input features %s are neither in fast_features (%s) nor in "
                "slow_features (%s); the policy ignores them", unused, self.fast_features,
                self.slow_features)

    @property
    def fast_dim(self) -> int:
        return sum(self._width(k, self.input_features or {}, "fast feature")
                   for k in self.fast_features)

    @property
    def slow_dim(self) -> int:
        return sum(self._width(k, self.input_features or {}, "slow feature")
                   for k in self.slow_features)

    @property
    def action_dim(self) -> int:
        return self._width(ACTION, self.output_features or {}, "action")
