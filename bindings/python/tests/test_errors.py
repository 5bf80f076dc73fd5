"""Bad input raises ValueError carrying the Rust error's text; nothing crashes."""

import math

import numpy as np
import pytest

import pir2

T, D = pir2.TrainSchedule, pir2.DelayDist


def test_schedule_errors():
    with pytest.raises(ValueError, match=r"invalid `alpha`: must be in \[0,1\], got 1.5"):
        T.pi_r2(alpha=1.5)
    with pytest.raises(ValueError, match=r"invalid `alpha`: must be in \[0,1\], got NaN"):
        T.pi_r2(alpha=math.nan)
    with pytest.raises(ValueError, match=r"invalid `jitter`: must be in \[0,1\], got NaN"):
        T.pi_r2(jitter=float("nan"))
    with pytest.raises(ValueError, match=r"invalid `delay.rate`: must be finite and >= 0, got NaN"):
        D.exponential(5, math.nan)
    with pytest.raises(ValueError, match=r"invalid `delay.max`: uniform delays need max >= 1"):
        D.uniform(0)
    with pytest.raises(ValueError, match=r"invalid `front.p`: must be in \[0,1\], got 2"):
        T.pi_r2(front="dropped", front_p=2.0)
    with pytest.raises(ValueError, match=r"invalid `front`"):
        T.pi_r2(front="sideways")
    # d_max > what H allows: the staircase error of the first delay that fails.
    with pytest.raises(ValueError, match=r"chunk length H = 8 is too short for delay d = 3 with the fresh alignment: need H >= 8|H = 8 is too short for delay d = 4"):
        T.pi_r2(n=2).draw(4, 8, 0)
    with pytest.raises(ValueError, match=r"invalid `delay.max`: train-time RTC needs d_max < H = 8, got 10"):
        T.train_time_rtc().draw(4, 8, 0)
    with pytest.raises(ValueError, match=r"invalid `batch`: must be >= 0, got -1"):
        T.standard_flow().draw(-1, 16, 0)
    with pytest.raises(ValueError, match=r"invalid `H`: must be >= 0, got -16"):
        T.standard_flow().draw(4, -16, 0)
    with pytest.raises(ValueError, match=r"invalid `seed`: must be an integer in \[0, 2\^64\)"):
        T.standard_flow().draw(4, 16, -3)
    with pytest.raises(ValueError, match=r"invalid `seed`"):
        T.standard_flow().draw(4, 16, "zero")
    with pytest.raises(ValueError, match=r"invalid `policy`: unknown policy"):
        T.for_policy("pi_r3")
    with pytest.raises(ValueError, match=r"invalid `recipe`"):
        T.for_policy("pi_r2", {"nfe": "two"})
    # A misspelt field is named, never ignored.
    with pytest.raises(ValueError, match=r'invalid `recipe`: unknown field "nfee"; the fields are .*nfe'):
        T.for_policy("pi_r2", {"nfee": 3})
    with pytest.raises(ValueError, match=r"invalid `schedule`"):
        T.from_json('{"kind": "nope"}')


def test_build_shape_errors():
    d = T.pi_r2(n=2).draw(4, 16, 0)
    with pytest.raises(ValueError, match=r"invalid `actions`: has shape \[4, 16\], expected \[B, H, A\] = \[4, 16, A\]"):
        d.build(np.zeros((4, 16)), np.zeros((4, 16)))
    with pytest.raises(ValueError, match=r"`eps` has length 128, expected 192"):
        d.build(np.zeros((4, 16, 3)), np.zeros((4, 16, 2)))
    with pytest.raises(ValueError, match=r"invalid `eps`: has shape \[4, 3, 16\], expected \[4, 16, 3\]"):
        d.build(np.zeros((4, 16, 3)), np.zeros((4, 3, 16)))


def test_buffer_errors():
    with pytest.raises(ValueError, match=r"chunk length H = 7 is too short for delay d = 3"):
        pir2.StreamBuffer(7, 2, nfe=2, max_delay=3)
    with pytest.raises(ValueError, match=r"invalid `action_dim`: must be at least 1"):
        pir2.StreamBuffer(16, 0)
    with pytest.raises(ValueError, match=r"invalid `nfe`: the paper alignment is the full-chunk ramp"):
        pir2.StreamBuffer(16, 1, nfe=2, alignment="paper")
    b = pir2.StreamBuffer(16, 2, nfe=2, max_delay=3)
    with pytest.raises(ValueError, match=r"invalid `step`: call plan\(d\) before step\(v\)"):
        b.step(np.zeros((16, 2)))
    with pytest.raises(ValueError, match=r"invalid `d`: delay 4 exceeds the buffer's max_delay 3"):
        b.plan(4)
    with pytest.raises(ValueError, match=r"invalid `d`: delay 17 exceeds"):
        b.plan(17)  # d > H
    with pytest.raises(ValueError, match=r"`clean chunk` has length 30, expected 32"):
        b.warm_start(1, np.zeros((15, 2)))
    with pytest.raises(ValueError, match=r"invalid `clean chunk`: has shape \[2, 16\], expected \[16, 2\]"):
        b.warm_start(1, np.zeros((2, 16)))
    b.plan(1)
    v = np.zeros((16, 2), dtype=np.float32)
    v[2, 1] = np.nan
    before = b.x
    with pytest.raises(ValueError, match=r"invalid `velocity`: non-finite value at flat index 5"):
        b.step(v)
    assert np.array_equal(b.x, before)                     # rejected before anything changes
    with pytest.raises(ValueError, match=r"`velocity` has length 31, expected 32"):
        b.step(np.zeros(31))
    with pytest.raises(ValueError, match=r"invalid `k`: cannot slide by 17 > H = 16"):
        b.slide(17)
    with pytest.raises(ValueError, match=r"invalid `p`: slot 16 is out of range for H = 16"):
        b.slot(16)
    with pytest.raises(ValueError, match=r"invalid `k`: warm start needs at least one step"):
        b.warm_start_with(1, 0, lambda x, t: x)


def test_rng_and_window_errors():
    with pytest.raises(ValueError, match=r"invalid `n`: must be an integer in \[1, 2\^64\)"):
        pir2.Rng(0).below(0)
    with pytest.raises(ValueError, match=r"invalid `state`: the all-zero state"):
        pir2.Rng.from_state([0, 0, 0, 0])
    with pytest.raises(ValueError, match=r"invalid `state`: must be four integers"):
        pir2.Rng.from_state([1, 2, 3, -4])
    with pytest.raises(ValueError, match=r"invalid `size`: must be >= 0, got -2"):
        pir2.gr00t_n17_tau(0, size=-2)
    w = pir2.LatencyWindow(4, 0, 20_000_000, 5)
    with pytest.raises(ValueError, match=r"invalid `latency_ns`: must be >= 0, got -5"):
        w.push(-5)
    with pytest.raises(ValueError, match=r"invalid `latency_ns`: must be integer nanoseconds"):
        w.push(np.array([1.5]))
    with pytest.raises(ValueError, match=r"invalid `w`: must be >= 0"):
        pir2.LatencyWindow(-1, 0, 1, 1)
