"""Type stubs of the `pir2` package (the compiled `pir2._pir2` extension)."""

from typing import Any, Callable, Iterator, Literal, Mapping, final, overload

from typing_extensions import Self

import numpy as np
import numpy.typing as npt

__version__: str

HIDDEN_FRONT_TAU: float
"""The `τ` a model sees on a hidden front slot (-1.0, outside [0, 1])."""
GR00T_N17_TAU_ALPHA: float
"""`α` of GR00T N1.7's flow-time law (1.5)."""
GR00T_N17_TAU_BETA: float
"""`β` of GR00T N1.7's flow-time law (1.0)."""
GR00T_N17_TAU_SCALE: float
"""Scale `s` of GR00T N1.7's flow-time law (0.999)."""

_F32 = npt.NDArray[np.float32]
_ArrayLike = npt.ArrayLike
_Alignment = Literal["fresh", "paper"]

@final
class Rng:
    """Seeded xoshiro256++ generator; `Rng(seed)` is Rust's `pir2_schedule::Rng::new(seed)`."""

    def __new__(cls, seed: int) -> Self: ...
    @staticmethod
    def derive(seed: int, stream: int) -> Rng:
        """An independent stream derived from `seed` and a stream id."""
    @staticmethod
    def from_state(state: tuple[int, int, int, int] | list[int]) -> Rng:
        """A generator continuing from a saved `state` (not all zero)."""
    @property
    def state(self) -> tuple[int, int, int, int]:
        """The full state (four unsigned 64-bit integers)."""
    @overload
    def next_u64(self, size: None = None) -> int: ...
    @overload
    def next_u64(self, size: int) -> npt.NDArray[np.uint64]: ...
    @overload
    def uniform(self, size: None = None) -> float: ...
    @overload
    def uniform(self, size: int) -> _F32: ...
    @overload
    def uniform_f64(self, size: None = None) -> float: ...
    @overload
    def uniform_f64(self, size: int) -> npt.NDArray[np.float64]: ...
    def below(self, n: int) -> int:
        """Uniform integer in `[0, n)` (`n >= 1`)."""
    @overload
    def normal(self, size: None = None) -> float: ...
    @overload
    def normal(self, size: int) -> _F32: ...

@overload
def gr00t_n17_tau(rng: int | Rng, size: None = None) -> float: ...
@overload
def gr00t_n17_tau(rng: int | Rng, size: int) -> _F32: ...
@overload
def gr00t_n17_tau_cdf(t: float) -> float: ...
@overload
def gr00t_n17_tau_cdf(t: _ArrayLike) -> npt.NDArray[np.float64]: ...

@final
class Staircase:
    """A validated staircase `τ*` for `(H, d, n)`; 0 = noise, 1 = clean."""

    def __new__(cls, horizon: int, delay: int, n: int | None = None, alignment: _Alignment = "fresh") -> Self: ...
    @staticmethod
    def fresh(horizon: int, delay: int, n: int | None = None) -> Staircase: ...
    @staticmethod
    def paper(horizon: int, delay: int) -> Staircase: ...
    @staticmethod
    def n_max(horizon: int, delay: int) -> int:
        """Largest valid `n` for `(H, d)` with the fresh alignment (0 when none)."""
    @property
    def horizon(self) -> int: ...
    @property
    def delay(self) -> int: ...
    @property
    def nfe(self) -> int: ...
    @property
    def alignment(self) -> _Alignment: ...
    @property
    def emitted(self) -> int: ...
    @overload
    def tau(self, p: None = None) -> _F32: ...
    @overload
    def tau(self, p: int) -> float: ...
    @overload
    def tau_after(self, p: None = None) -> _F32: ...
    @overload
    def tau_after(self, p: int) -> float: ...
    def at_delay(self, delay: int, requested_n: int | None = None) -> Staircase: ...
    def __array__(self, dtype: Any = None, copy: bool | None = None) -> _F32: ...
    def __len__(self) -> int: ...
    def __eq__(self, other: object, /) -> bool: ...

def staircase(horizon: int, delay: int, n: int | None = None, alignment: _Alignment = "fresh") -> _F32:
    """Per-position `τ*` for `(H, d, n)` as a `float32` array `[H]`."""

@final
class DelayDist:
    """Distribution of the training delay `d`."""

    @staticmethod
    def uniform(max: int) -> DelayDist:
        """`d ~ U{1..max}`."""
    @staticmethod
    def exponential(max: int, rate: float) -> DelayDist:
        """`p(d = k) ∝ exp(−rate·k)` over `{0..max}`."""
    @property
    def kind(self) -> Literal["uniform", "exponential"]: ...
    @property
    def max(self) -> int: ...
    @property
    def rate(self) -> float | None: ...
    def pmf(self, k: int) -> float: ...
    @overload
    def sample(self, rng: int | Rng, size: None = None) -> int: ...
    @overload
    def sample(self, rng: int | Rng, size: int) -> npt.NDArray[np.int64]: ...
    def __eq__(self, other: object, /) -> bool: ...

@final
class Draws:
    """A batch of training draws (`B` samples, chunk length `H`)."""

    tau: _F32
    """True noise level per position, `[B, H]`."""
    mask: _F32
    """Loss mask per position, `[B, H]` (0 on the front)."""
    delay: npt.NDArray[np.int64]
    """Drawn delay per sample, `[B]` (0 for unmasked draws)."""
    hidden: npt.NDArray[np.bool_]
    """Front hidden from the model, `[B]`."""
    @property
    def horizon(self) -> int: ...
    def build(self, actions: _ArrayLike, eps: _ArrayLike) -> tuple[_F32, _F32, _F32]:
        """`(x [B,H,A], tau_in [B,H], target [B,H,A])` from `actions` and `eps` `[B,H,A]`."""
    def __len__(self) -> int: ...

_PolicyName = Literal[
    "pi_r2", "pi_r2_hidden", "pi_r2_full", "rtc", "flow", "pi_r2_zero_delay", "pi_r2_zero_delay_full"
]

@final
class TrainSchedule:
    """A training schedule (Rust `pir2_schedule::train::TrainSchedule`)."""

    @staticmethod
    def pi_r2(
        alpha: float = 0.2,
        delay: DelayDist | None = None,
        n: int | None = None,
        alignment: _Alignment = "fresh",
        jitter: float = 0.0,
        front: Literal["visible", "hidden", "dropped"] = "visible",
        front_p: float | None = None,
    ) -> TrainSchedule: ...
    @staticmethod
    def train_time_rtc(delay: DelayDist | None = None) -> TrainSchedule: ...
    @staticmethod
    def standard_flow() -> TrainSchedule: ...
    @staticmethod
    def gr00t_flow() -> TrainSchedule: ...
    @staticmethod
    def streaming_diffusion() -> TrainSchedule: ...
    @staticmethod
    def for_policy(
        policy: _PolicyName, recipe: Literal["default", "paper_sim"] | Mapping[str, Any] | None = None
    ) -> TrainSchedule: ...
    @staticmethod
    def from_json(text: str) -> TrainSchedule: ...
    def to_json(self) -> str: ...
    @property
    def kind(self) -> Literal["pi_r2", "train_time_rtc", "standard_flow", "gr00t_flow", "streaming_diffusion"]: ...
    def validate(self, horizon: int) -> None: ...
    def draw(self, batch: int, horizon: int, rng: int | Rng) -> Draws:
        """`batch` successive Rust `TrainSchedule::draw` calls on one generator."""
    def __eq__(self, other: object, /) -> bool: ...

@final
class Emitted:
    """Slots `[start, start + len)` are clean: the actions to execute after the front."""

    @property
    def start(self) -> int: ...
    @property
    def len(self) -> int: ...
    def __iter__(self) -> Iterator[int]: ...

@final
class StreamBuffer:
    """The streaming inference buffer: `plan(d)`, `step(v)`, `slide(k)`."""

    def __new__(
        cls,
        horizon: int = 16,
        action_dim: int = 1,
        nfe: int | None = None,
        alignment: _Alignment = "fresh",
        front: Literal["visible", "hidden"] = "visible",
        max_delay: int = 5,
        seed: int | None = None,
    ) -> Self: ...
    @property
    def config(self) -> dict[str, Any]: ...
    @property
    def horizon(self) -> int: ...
    @property
    def action_dim(self) -> int: ...
    def staircase(self, d: int) -> Staircase: ...
    @property
    def x(self) -> _F32: ...
    @property
    def tau(self) -> _F32: ...
    @property
    def xhat(self) -> _F32: ...
    @property
    def delta(self) -> _F32: ...
    @property
    def model_x(self) -> _F32: ...
    @property
    def model_tau(self) -> _F32: ...
    def slot(self, p: int) -> _F32: ...
    def xhat_slot(self, p: int) -> _F32: ...
    @property
    def index(self) -> int: ...
    @property
    def clean_prefix(self) -> int: ...
    def warm_start(self, d0: int, clean: _ArrayLike) -> None: ...
    def warm_start_with(self, d0: int, k: int, model: Callable[[_F32, _F32], _ArrayLike]) -> None: ...
    def plan(self, d: int) -> None: ...
    def step(self, v: _ArrayLike) -> Emitted: ...
    def remap(self, xhat_new: _ArrayLike) -> None: ...
    def slide(self, k: int) -> None: ...

@final
class LatencyWindow:
    """Rolling latency window: `d = max(1, round(mean / period))`, clamped to `d_max`."""

    def __new__(cls, w: int, warmup: int, period_ns: int, d_max: int, initial_delay: int | None = None) -> Self: ...
    def push(self, latency_ns: int | _ArrayLike) -> None: ...
    @property
    def mean(self) -> float | None: ...
    @property
    def delay(self) -> int: ...
    def is_empty(self) -> bool: ...
    def __len__(self) -> int: ...

__all__ = [
    "GR00T_N17_TAU_ALPHA",
    "GR00T_N17_TAU_BETA",
    "GR00T_N17_TAU_SCALE",
    "HIDDEN_FRONT_TAU",
    "DelayDist",
    "Draws",
    "Emitted",
    "LatencyWindow",
    "Rng",
    "Staircase",
    "StreamBuffer",
    "TrainSchedule",
    "__version__",
    "gr00t_n17_tau",
    "gr00t_n17_tau_cdf",
    "staircase",
]
