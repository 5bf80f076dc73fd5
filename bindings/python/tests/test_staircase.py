"""Staircase invariants (docs/method.md §1 of the repository)."""

import numpy as np
import pytest

import pir2


def cases():
    for h in range(1, 25):
        for d in range(0, 9):
            n_max = pir2.Staircase.n_max(h, d)
            for n in range(1, n_max + 1):
                yield h, d, n


def test_docs_example():
    assert pir2.staircase(8, 2, 2).tolist() == [1.0, 1.0, 0.75, 0.5, 0.25, 0.0, 0.0, 0.0]
    p = pir2.Staircase.paper(8, 2)
    assert p.tau(2) == 1.0 and p.tau(6) == 0.0
    assert pir2.Staircase.n_max(16, 1) == 15 and pir2.Staircase.n_max(16, 3) == 3
    assert pir2.Staircase.n_max(16, 0) == 16 and pir2.Staircase.n_max(4, 2) == 0


def test_fresh_invariants():
    count = 0
    for h, d, n in cases():
        s = pir2.Staircase(h, d, n)
        t = s.tau()
        assert t.dtype == np.float32 and t.shape == (h,)
        e = max(d, 1)
        ramp = n * e - 1
        assert (t[:d] == 1.0).all()                       # clean front
        assert ((0.0 <= t) & (t <= 1.0)).all()
        assert (np.diff(t) <= 0).all()                    # never increases along the chunk
        assert (t[d + ramp:] == 0.0).all()                # noise tail
        assert (t[d:d + ramp] < 1.0).all() and (t[d:d + ramp] > 0.0).all()
        assert (t[h - e:] == 0.0).all()                   # at least e noise slots (fresh)
        after = s.tau_after()
        assert (after[:e] == 1.0).all()
        assert np.array_equal(after[e:], t[:h - e])       # the staircase shifted by e
        assert s.horizon == h and s.delay == d and s.nfe == n and s.emitted == e
        assert np.array_equal(np.asarray(s), t) and len(s) == h
        assert [s.tau(p) for p in range(h + 2)] == t.tolist() + [0.0, 0.0]
        count += 1
    assert count > 300


def test_full_ramp_and_paper():
    s = pir2.Staircase(16, 3)
    assert s.nfe == pir2.Staircase.n_max(16, 3)
    p = pir2.Staircase(10, 2, alignment="paper")
    t = p.tau()
    assert t[:3].tolist() == [1.0, 1.0, 1.0] and t[8] == 0.0
    assert abs(t[4] - (1 - 2 / 6)) < 1e-7
    assert pir2.Staircase(16, 2, None, "paper") == pir2.Staircase.paper(16, 2)


def test_at_delay_caps_n():
    s = pir2.Staircase(16, 1, 4)
    t = s.at_delay(3, 4)
    assert t.delay == 3 and t.nfe == 3  # n_max(16, 3) = 3


def test_invalid_staircases_raise_the_rust_text():
    with pytest.raises(ValueError, match=r"n = 4 NFEs per action is out of range for H = 16, d = 3: need 1 <= n <= n_max = 3"):
        pir2.Staircase(16, 3, 4)
    with pytest.raises(ValueError, match=r"chunk length H = 7 is too short for delay d = 3 with the fresh alignment: need H >= 8"):
        pir2.Staircase(7, 3)
    with pytest.raises(ValueError, match=r"chunk length H = 4 is too short for delay d = 5"):
        pir2.staircase(4, 5)  # d > H
    with pytest.raises(ValueError, match=r"invalid `n`: the paper alignment is the full-chunk ramp"):
        pir2.Staircase(10, 2, 4, "paper")
    with pytest.raises(ValueError, match=r"invalid `H`: chunk length must be at least 1"):
        pir2.Staircase(0, 0)
    with pytest.raises(ValueError, match=r"invalid `d`: must be >= 0, got -1"):
        pir2.Staircase(8, -1)
    with pytest.raises(ValueError, match=r"invalid `alignment`"):
        pir2.Staircase(8, 1, alignment="late")
