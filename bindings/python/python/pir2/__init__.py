"""pir2: πR² (reactive real-time flow policies) for Python trainers.

The numbers come from pir2's Rust core (``pir2-schedule`` and ``pir2-runtime``) through a
compiled extension; nothing here needs torch. With the same seed every draw is bit-identical
to the Rust crates'.

- :class:`Staircase` / :func:`staircase`: the per-position noise schedule ``τ*`` for ``(H, d, n)``;
- :class:`TrainSchedule`: the training draws of every policy family (πR², front hidden, full
  ramp, train-time RTC, standard flow, GR00T N1.7 flow, streaming diffusion), drawn as numpy
  arrays by :meth:`TrainSchedule.draw`; :class:`DelayDist` for their delays;
- :func:`gr00t_n17_tau`: GR00T N1.7's Beta flow-time law;
- :class:`StreamBuffer`: the streaming inference buffer (plan / step / slide);
- :class:`LatencyWindow`: the runtime's rolling latency window that measures ``d``;
- :class:`Rng`: the seeded generator behind all of them.

:mod:`pir2.gr00t` (needs torch) turns GR00T N1.7's action head into the paper's per-position
form and fine-tunes it with these draws in PyTorch.

Convention: ``τ = 0`` is pure noise, ``τ = 1`` is clean, ``x = (1 − τ)·ε + τ·a``. Invalid
input raises ``ValueError`` carrying the Rust error's text.
"""

from ._pir2 import (
    GR00T_N17_TAU_ALPHA,
    GR00T_N17_TAU_BETA,
    GR00T_N17_TAU_SCALE,
    HIDDEN_FRONT_TAU,
    DelayDist,
    Draws,
    Emitted,
    LatencyWindow,
    Rng,
    Staircase,
    StreamBuffer,
    TrainSchedule,
    __version__,
    gr00t_n17_tau,
    gr00t_n17_tau_cdf,
    staircase,
)

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
