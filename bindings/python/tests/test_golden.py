"""Same seed → the same bits as the Rust crates, on thousands of draws.

`golden_draws.json` is written and checked by the pure-Rust test
`tests/tests/python_golden.rs` (pir2-schedule / pir2-runtime, no Python involved); here the
same streams are drawn through the `pir2` package and compared by SHA-256 of their
little-endian bytes.
"""

import hashlib

import numpy as np
import pytest

import pir2


def sha(a: np.ndarray, dtype: str) -> str:
    return hashlib.sha256(np.ascontiguousarray(a, dtype=dtype).tobytes()).hexdigest()


def test_every_schedule_kind_is_covered(golden):
    kinds = {pir2.TrainSchedule.from_json(__import__("json").dumps(c["schedule"])).kind
             for c in golden["schedules"]}
    assert kinds == {"pi_r2", "train_time_rtc", "standard_flow", "gr00t_flow", "streaming_diffusion"}


@pytest.mark.parametrize("as_rng", [False, True])
def test_schedule_draws_are_bit_identical(golden, as_rng):
    import json

    for case in golden["schedules"]:
        s = pir2.TrainSchedule.from_json(json.dumps(case["schedule"]))
        rng = pir2.Rng(case["seed"]) if as_rng else case["seed"]
        d = s.draw(case["batch"], case["horizon"], rng)
        name = case["name"]
        assert d.tau.shape == (case["batch"], case["horizon"]) and d.tau.dtype == np.float32
        assert sha(d.tau, "<f4") == case["tau_sha256"], name
        assert sha(d.mask, "<f4") == case["mask_sha256"], name
        assert sha(d.delay, "<i8") == case["delay_sha256"], name
        assert sha(d.hidden, "u1") == case["hidden_sha256"], name
        assert d.tau[0].tolist() == [np.float32(x) for x in case["tau_first_row"]], name
        if as_rng:
            assert list(rng.state) == [int(x) for x in case["state_after"]], name


def test_python_constructors_give_the_rust_schedules(golden):
    import json

    by_name = {c["name"]: pir2.TrainSchedule.from_json(json.dumps(c["schedule"]))
               for c in golden["schedules"]}
    T, D = pir2.TrainSchedule, pir2.DelayDist
    built = {
        "pi_r2_default": T.pi_r2(),
        "pi_r2_n2_jitter_dropped_exponential": T.pi_r2(
            n=2, jitter=0.1, front="dropped", front_p=0.3, delay=D.exponential(5, 1.0)),
        "pi_r2_paper": T.pi_r2(alignment="paper"),
        "train_time_rtc": T.train_time_rtc(D.uniform(10)),
        "standard_flow": T.standard_flow(),
        "gr00t_flow": T.gr00t_flow(),
        "streaming_diffusion": T.streaming_diffusion(),
        "policy_pi_r2": T.pi_r2(n=2),
        "policy_pi_r2_hidden": T.pi_r2(n=2, front="hidden"),
        "policy_pi_r2_full": T.pi_r2(alignment="paper"),
        "policy_rtc": T.train_time_rtc(D.uniform(6)),
        "policy_flow": T.standard_flow(),
        "policy_pi_r2_zero_delay": T.pi_r2(n=2, delay=D.exponential(0, 1.0)),
        "policy_pi_r2_zero_delay_full": T.pi_r2(delay=D.exponential(0, 1.0)),
    }
    assert set(built) == set(by_name)
    for name, s in built.items():
        assert s == by_name[name], name
        if name.startswith("policy_"):
            assert T.for_policy(name[len("policy_"):]) == by_name[name], name


def test_gr00t_tau_stream(golden):
    g = golden["gr00t_n17_tau"]
    t = pir2.gr00t_n17_tau(g["seed"], size=g["count"])
    assert t.dtype == np.float32
    assert sha(t, "<f4") == g["sha256"]
    assert t[:4].tolist() == [np.float32(x) for x in g["first"]]
    # One at a time on a shared generator: the same stream.
    r = pir2.Rng(g["seed"])
    assert [pir2.gr00t_n17_tau(r) for _ in range(4)] == t[:4].tolist()


def test_rng_streams(golden):
    g = golden["rng"]
    r = pir2.Rng(g["seed"])
    assert sha(r.uniform(size=g["uniform_count"]), "<f4") == g["uniform_sha256"]
    assert sha(r.normal(size=g["normal_count_after_uniform"]), "<f4") == g["normal_sha256"]


def test_stream_buffer_trajectory(golden):
    g = golden["stream_buffer"]
    h, a = g["horizon"], g["action_dim"]
    b = pir2.StreamBuffer(h, a, nfe=g["nfe"], max_delay=g["max_delay"], seed=g["seed"])
    i = np.arange(h * a)
    clean = (i.astype(np.float32) * np.float32(0.125) - np.float32(1.0)).reshape(h, a)
    v = ((i % 7).astype(np.float32) * np.float32(0.25) - np.float32(0.75)).reshape(h, a)
    b.warm_start(1, clean)
    parts, emitted = [], []
    for k in range(g["calls"]):
        b.plan(k % 3 + 1)
        e = b.step(v)
        emitted.append([e.start, e.len])
        parts += [b.x.ravel(), b.tau, b.xhat.ravel()]
        b.slide(e.len)
    parts.append(b.x.ravel())
    assert emitted == g["emitted"]
    assert sha(np.concatenate(parts), "<f4") == g["sha256"]


def test_latency_window(golden):
    g = golden["latency_window"]
    w = pir2.LatencyWindow(g["w"], g["warmup"], g["period_ns"], g["d_max"])
    delays = []
    for i in range(40):
        w.push(900_000_000 * (i == 0) + (i * 7_000_000) % 110_000_000)
        delays.append(w.delay)
    assert delays == g["delays"]
