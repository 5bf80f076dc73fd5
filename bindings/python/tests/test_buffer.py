"""StreamBuffer invariants (plan / step / slide) and the latency window."""

import numpy as np
import pytest

import pir2


def exact_velocity(buf, target):
    """v = (a − x)/(1 − τ): one Euler step of size Δτ lands each slot on its ramp value."""
    t = buf.tau[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.where(t < 1, (target - buf.x) / (1 - t), 0.0)
    return v.astype(np.float32)


def test_docs_example():
    buf = pir2.StreamBuffer(horizon=8, action_dim=1, nfe=2, max_delay=2, seed=0)
    target = np.full((8, 1), 0.3, dtype=np.float32)
    buf.warm_start(1, target)
    assert buf.tau.tolist() == [1.0, 0.5, 0, 0, 0, 0, 0, 0]
    buf.plan(1)
    start, n = buf.step(exact_velocity(buf, target))
    assert (start, n) == (1, 1)
    assert abs(buf.slot(1)[0] - 0.3) < 1e-6
    buf.slide(1)
    assert buf.tau.tolist() == [1.0, 0.5, 0, 0, 0, 0, 0, 0]
    assert buf.index == 1


def test_steady_cycle_reproduces_the_staircase():
    buf = pir2.StreamBuffer(16, 2, nfe=2, max_delay=3, seed=1)
    buf.warm_start(2, np.zeros((16, 2)))
    want = buf.staircase(2).tau()
    for _ in range(20):
        buf.plan(2)
        e = buf.step(np.full((16, 2), 0.1))
        assert (e.start, e.len) == (2, 2)
        assert buf.tau[2:4].tolist() == [1.0, 1.0]
        buf.slide(2)
        assert np.array_equal(buf.tau, want)


@pytest.mark.parametrize("front", ["visible", "hidden"])
def test_changing_delays_keep_the_invariants(front):
    h, a = 16, 2
    buf = pir2.StreamBuffer(h, a, nfe=2, max_delay=4, front=front, seed=3)
    buf.warm_start(1, np.zeros((h, a)))
    rng = np.random.default_rng(0)
    ds = rng.integers(1, 5, size=300)
    for i, d in enumerate(ds):
        d = int(d)
        before = buf.tau
        buf.plan(d)
        assert (buf.delta >= 0).all()                     # nothing moves down
        assert buf.clean_prefix >= d                       # the front is committed
        mt = buf.model_tau
        if front == "hidden":
            assert (mt[:d] == pir2.HIDDEN_FRONT_TAU).all() and (buf.model_x[:d] == 0).all()
        else:
            assert np.array_equal(mt, buf.tau)
        e = buf.step(rng.standard_normal((h, a)).astype(np.float32))
        t = buf.tau
        assert (t >= before).all()                         # τ only grows within a call
        assert ((0 <= t) & (t <= 1)).all()
        assert (t[: e.start + e.len] == 1).all()           # emitted slots are clean
        assert np.array_equal(buf.x[e.start:e.start + e.len], buf.xhat[e.start:e.start + e.len])
        buf.slide(e.len)
    # After ⌈H/d⌉ calls at constant d the buffer is the d-staircase again.
    for _ in range(h):
        buf.plan(3)
        buf.step(np.zeros((h, a)))
        buf.slide(3)
    assert np.array_equal(buf.tau, buf.staircase(3).tau())


def test_same_seed_same_noise():
    a = pir2.StreamBuffer(16, 3, nfe=2, seed=5)
    b = pir2.StreamBuffer(16, 3, nfe=2, seed=5)
    c = pir2.StreamBuffer(16, 3, nfe=2, seed=6)
    assert np.array_equal(a.x, b.x) and not np.array_equal(a.x, c.x)
    assert a.x.dtype == np.float32 and a.x.shape == (16, 3)


def test_remap_and_warm_start_with():
    buf = pir2.StreamBuffer(8, 2, nfe=2, max_delay=2, seed=3)
    buf.warm_start(1, np.full((8, 2), 0.25))
    x0, h0, tau = buf.x, buf.xhat, buf.tau
    buf.remap(buf.xhat)                                    # identity: no bit changes
    assert np.array_equal(buf.x, x0) and np.array_equal(buf.xhat, h0)
    z = h0 + np.float32(0.5) + np.arange(8, dtype=np.float32)[:, None]
    buf.remap(z)
    assert np.array_equal(buf.xhat, z)
    clean = tau >= 1
    assert np.array_equal(buf.x[clean], z[clean])
    np.testing.assert_allclose(buf.x - tau[:, None] * buf.xhat, x0 - tau[:, None] * h0, atol=1e-5)

    calls = []

    def model(x, t):
        calls.append((x.shape, t.shape, float(t[0])))
        return np.full_like(x, 0.5)

    buf.warm_start_with(1, 4, model)
    assert [c[2] for c in calls] == [0.0, 0.25, 0.5, 0.75]
    assert calls[0][:2] == ((8, 2), (8,))

    def broken(x, t):
        raise RuntimeError("model failed")

    with pytest.raises(RuntimeError, match="model failed"):
        buf.warm_start_with(1, 2, broken)
    with pytest.raises(ValueError, match=r"`velocity` has length 3, expected 16"):
        buf.warm_start_with(1, 2, lambda x, t: np.zeros(3))


def test_latency_window_docs_example():
    w = pir2.LatencyWindow(4, 1, 20_000_000, 5)
    assert w.delay == 1 and w.mean is None and w.is_empty()
    w.push(900_000_000)                                    # cold call: ignored
    assert len(w) == 0
    w.push(np.full(4, 25_000_000))
    assert w.delay == 1 and len(w) == 4
    for _ in range(4):
        w.push(45_000_000)
    assert w.delay == 2 and w.mean == 45_000_000.0
    assert pir2.LatencyWindow(4, 0, 20_000_000, 5, initial_delay=3).delay == 3
