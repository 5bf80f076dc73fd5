"""Training draws: shapes, invariants per schedule, `Draws.build`, stream continuity."""

import subprocess
import sys

import numpy as np
import pytest

import pir2

T, D = pir2.TrainSchedule, pir2.DelayDist


def test_import_needs_no_torch():
    code = "import sys, pir2; pir2.TrainSchedule.pi_r2().draw(4, 16, 0); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_shapes_and_dtypes():
    d = T.pi_r2(n=2).draw(64, 16, 0)
    assert len(d) == 64 and d.horizon == 16
    assert d.tau.shape == d.mask.shape == (64, 16)
    assert d.tau.dtype == d.mask.dtype == np.float32
    assert d.delay.dtype == np.int64 and d.hidden.dtype == np.bool_
    assert T.standard_flow().draw(0, 16, 0).tau.shape == (0, 16)


def test_pi_r2_invariants():
    n, h = 2, 16
    d = T.pi_r2(n=n, alpha=0.2).draw(4000, h, 7)
    warm = (d.delay == 0)
    assert 0.15 < warm.mean() < 0.25                      # alpha = 0.2 warm-up branch
    for i in range(len(d)):
        k = int(d.delay[i])
        if k == 0:                                        # warm-up: one shared τ, no mask
            assert (d.tau[i] == d.tau[i, 0]).all() and (d.mask[i] == 1).all()
        else:                                             # staircase at delay k, n capped
            assert 1 <= k <= 5
            s = pir2.Staircase(h, k, min(n, pir2.Staircase.n_max(h, k)))
            assert np.array_equal(d.tau[i], s.tau())
            assert (d.mask[i, :k] == 0).all() and (d.mask[i, k:] == 1).all()
    assert not d.hidden.any()
    assert set(np.unique(d.delay[~warm])) == {1, 2, 3, 4, 5}


def test_hidden_and_dropped_fronts():
    d = T.pi_r2(n=2, front="hidden").draw(500, 16, 1)
    assert np.array_equal(d.hidden, d.delay > 0)
    d = T.pi_r2(n=2, front="dropped", front_p=0.5).draw(4000, 16, 2)
    frac = d.hidden[d.delay > 0].mean()
    assert 0.45 < frac < 0.55 and not d.hidden[d.delay == 0].any()


def test_jitter_stays_in_range():
    d = T.pi_r2(n=2, jitter=0.3, alpha=0.0).draw(1000, 16, 3)
    assert ((d.tau >= 0) & (d.tau <= 1)).all()
    for i in range(20):
        k = int(d.delay[i])
        assert (d.tau[i, :k] == 1).all()                 # the front is never jittered


def test_baselines():
    h = 16
    d = T.train_time_rtc(D.uniform(10)).draw(1000, h, 4)
    assert ((1 <= d.delay) & (d.delay <= 10)).all()
    for i in range(50):
        k = int(d.delay[i])
        assert (d.tau[i, :k] == 1).all() and (d.mask[i, :k] == 0).all()
        assert (d.tau[i, k:] == d.tau[i, k]).all()
    f = T.standard_flow().draw(1000, h, 5)
    assert (f.tau == f.tau[:, :1]).all() and (f.mask == 1).all() and (f.delay == 0).all()
    g = T.gr00t_flow().draw(20000, h, 6)
    assert (g.tau == g.tau[:, :1]).all() and (g.tau < pir2.GR00T_N17_TAU_SCALE + 1e-7).all()
    assert abs(g.tau[:, 0].mean() - 0.4 * 0.999) < 0.01   # s·Beta(1, 1.5) has mean 0.4·s
    sd = T.streaming_diffusion().draw(100, h, 7)
    assert (np.diff(sd.tau, axis=1) < 0).all() and (sd.mask == 1).all()


def test_gr00t_law():
    t = pir2.gr00t_n17_tau(1, size=200_000).astype(np.float64)
    t.sort()
    ks = np.max(np.abs(pir2.gr00t_n17_tau_cdf(t) - np.arange(1, t.size + 1) / t.size))
    assert ks < 1.95 / np.sqrt(t.size)
    assert pir2.gr00t_n17_tau_cdf(0.0) == 0.0 and pir2.gr00t_n17_tau_cdf(1.0) == 1.0
    assert pir2.gr00t_n17_tau_cdf(np.zeros((2, 3))).shape == (2, 3)
    assert (pir2.GR00T_N17_TAU_ALPHA, pir2.GR00T_N17_TAU_BETA) == (1.5, 1.0)


def test_rng_object_continues_the_stream():
    s = T.pi_r2(n=2, jitter=0.1)
    whole = s.draw(300, 16, 42)
    r = pir2.Rng(42)
    a, b = s.draw(100, 16, r), s.draw(200, 16, r)
    assert np.array_equal(np.concatenate([a.tau, b.tau]), whole.tau)
    assert np.array_equal(np.concatenate([a.delay, b.delay]), whole.delay)
    saved = pir2.Rng.from_state(r.state)
    assert saved.next_u64() == r.next_u64()
    assert pir2.Rng.derive(1, 2).state != pir2.Rng(1).state


def test_build_matches_the_formula():
    h, a, b = 16, 3, 200
    d = T.pi_r2(n=2, front="dropped", front_p=0.5).draw(b, h, 8)
    rng = np.random.default_rng(0)
    act = rng.standard_normal((b, h, a)).astype(np.float32)
    eps = rng.standard_normal((b, h, a)).astype(np.float32)
    x, tau_in, target = d.build(act, eps)
    assert x.shape == target.shape == (b, h, a) and tau_in.shape == (b, h)
    t = d.tau[:, :, None]
    want = (np.float32(1) - t) * eps + t * act
    hide = d.hidden[:, None] & (np.arange(h)[None, :] < d.delay[:, None])
    want[hide] = 0.0
    np.testing.assert_array_equal(x, want)
    np.testing.assert_array_equal(target, act - eps)
    np.testing.assert_array_equal(tau_in, np.where(hide, pir2.HIDDEN_FRONT_TAU, d.tau))
    vis = ~hide & (d.mask == 0)
    assert np.array_equal(x[vis], act[vis])               # a visible front carries ground truth


def test_json_round_trip_and_for_policy():
    s = T.pi_r2(n=3, jitter=0.05, delay=D.exponential(4, 0.5))
    assert T.from_json(s.to_json()) == s
    assert T.for_policy("pi_r2_full").kind == "pi_r2"
    assert T.for_policy("rtc", "paper_sim") == T.train_time_rtc(D.exponential(10, 1.0))
    assert T.for_policy("rtc", {"rtc_d_max": 8}) == T.train_time_rtc(D.uniform(8))
    exp = T.for_policy("pi_r2", {"delays": {"law": "exponential", "rate": 1.0}})
    assert exp == T.pi_r2(n=2, delay=D.exponential(5, 1.0))


def test_delay_dist():
    u = D.uniform(5)
    assert u.kind == "uniform" and u.max == 5 and u.rate is None
    assert u.pmf(0) == 0.0 and abs(sum(u.pmf(k) for k in range(6)) - 1) < 1e-12
    e = D.exponential(5, 0.7)
    assert abs(sum(e.pmf(k) for k in range(6)) - 1) < 1e-12
    s = e.sample(3, size=20000)
    assert s.dtype == np.int64 and s.min() == 0 and s.max() == 5
    freq = np.bincount(s, minlength=6) / s.size
    assert np.allclose(freq, [e.pmf(k) for k in range(6)], atol=0.015)
