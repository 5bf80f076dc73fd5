#!/usr/bin/env python3
"""A servo-j session with UFACTORY's own Python SDK (xarm-python-sdk 1.18.4) as the client.

Run by `pir2-robots/tests/xarm_sdk.rs` against the pir2 xArm emulator on loopback ports.
The SDK's port numbers are module constants; they are overridden here (and the report
parser picked by port number is mapped back to the standard port) so that the emulator
can listen on unprivileged, OS-chosen ports.

Session: connect (rich report stream, the SDK default), motion_enable, set_mode(1),
set_state(0), 3 s of set_servo_angle_j at 100 Hz with a different sinusoid per joint,
hold, disconnect. Two more SDK instances watch the "real" (30003) and "normal" (30001)
report streams during the session. Checks:

* every SDK call returns 0;
* axis == 6, the arm reports mode 1 and no error after the set-up;
* get_servo_angle and every report stream's joint angles track the commanded angles
  within 0.03 rad at some lag <= 0.25 s;
* 0.5 s after the last command the arm holds it within 0.005 rad (get_servo_angle and
  the rich report stream);
* joint torques arrive (7 finite values per report).

Exits 1 with one line per failed check, 0 if all pass; prints a summary either way.
"""

import argparse
import faulthandler
import json
import math
import sys
import threading
import time

TRACK_TOL = 0.03
LAG_MAX = 0.25
HOLD_TOL = 0.005
RATE_HZ = 100.0
SECONDS = 3.0
AMPL = [0.20, 0.15, 0.12, 0.25, 0.18, 0.30]
FREQ = [0.50, 0.70, 0.90, 0.40, 0.60, 0.80]


def parse_args():
    p = argparse.ArgumentParser()
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--cmd-port", type=int, required=True)
    p.add_argument("--normal-port", type=int, required=True)
    p.add_argument("--rich-port", type=int, required=True)
    p.add_argument("--real-port", type=int, required=True)
    p.add_argument("--connect-wait", type=float, default=5.0,
                   help="seconds to wait for the first report of each stream")
    p.add_argument("--deadline", type=float, default=45.0,
                   help="seconds after which the session is aborted (stacks dumped, exit 1)")
    return p.parse_args()


def patch_ports(a):
    """Point the SDK at our ports; keep its port-keyed report parser selection working."""
    from xarm.core.config.x_config import XCONF
    from xarm.x3.report import ReportDataStructure

    conf = XCONF.SocketConf
    conf.TCP_CONTROL_PORT = a.cmd_port
    conf.TCP_REPORT_NORM_PORT = a.normal_port
    conf.TCP_REPORT_RICH_PORT = a.rich_port
    conf.TCP_REPORT_REAL_PORT = a.real_port
    standard = {a.normal_port: 30001, a.rich_port: 30002, a.real_port: 30003}
    create = ReportDataStructure.create.__func__

    def create_mapped(cls, sock_port, **kw):
        return create(cls, standard.get(sock_port, sock_port), **kw)

    ReportDataStructure.create = classmethod(create_mapped)


class Recorder:
    """Joint angles from one SDK instance's report stream, with arrival times."""

    def __init__(self):
        self.lock = threading.Lock()
        self.samples = []

    def __call__(self, msg):
        joints = msg.get("joints")
        if joints is not None:
            with self.lock:
                self.samples.append((time.monotonic(), list(joints[:6])))

    def snapshot(self):
        with self.lock:
            return list(self.samples)


def command_at(cmds, q0, t):
    """The newest command sent at or before t (q0 before the first one)."""
    lo, hi = 0, len(cmds)
    while lo < hi:
        mid = (lo + hi) // 2
        if cmds[mid][0] <= t:
            lo = mid + 1
        else:
            hi = mid
    return cmds[lo - 1][1] if lo > 0 else q0


def tracking(samples, cmds, q0):
    """(best max-error over lags 0..LAG_MAX, that lag) for samples during the motion."""
    if not samples:
        return math.inf, None
    best = (math.inf, None)
    steps = int(LAG_MAX * 1000 / 5)
    for k in range(steps + 1):
        lag = k * 0.005
        err = 0.0
        for t, q in samples:
            c = command_at(cmds, q0, t - lag)
            err = max(err, max(abs(q[i] - c[i]) for i in range(6)))
        if err < best[0]:
            best = (err, lag)
    return best


def log(msg):
    print(f"[sdk-session {time.monotonic():.3f}] {msg}", file=sys.stderr, flush=True)


def main():
    a = parse_args()
    # A hung SDK call must not hang the test: dump every thread's stack and exit non-zero.
    faulthandler.dump_traceback_later(a.deadline, exit=True)
    patch_ports(a)
    from xarm.wrapper import XArmAPI

    fails = []
    summary = {}

    def check(ok, msg):
        if not ok:
            fails.append(msg)
        return ok

    def call(name, code):
        check(code == 0, f"{name} returned {code}, expected 0")
        return code

    # Watchers first: they never command, they only parse their report stream.
    watchers = {}
    for kind in ("real", "normal"):
        log(f"connecting a {kind}-report watcher")
        w = XArmAPI(a.host, is_radian=True, report_type=kind, forbid_uds=True)
        rec = Recorder()
        w.register_report_location_callback(rec, report_cartesian=False, report_joints=True)
        watchers[kind] = (w, rec)

    log("connecting the session (rich report stream)")
    arm = XArmAPI(a.host, is_radian=True, forbid_uds=True)  # report_type "rich" (default)
    rich = Recorder()
    arm.register_report_location_callback(rich, report_cartesian=False, report_joints=True)
    check(arm.connected, "the SDK did not connect to the command port")
    check(arm.axis == 6, f"the SDK reads axis = {arm.axis}, expected 6 (version {arm.version!r})")
    summary["version"] = arm.version
    summary["version_number"] = list(arm.version_number)
    summary["axis"] = arm.axis
    summary["device_type"] = arm.device_type

    deadline = time.monotonic() + a.connect_wait
    recs = {"rich": rich, **{k: r for k, (_, r) in watchers.items()}}
    while time.monotonic() < deadline and not all(r.snapshot() for r in recs.values()):
        time.sleep(0.02)
    for kind, rec in recs.items():
        check(rec.snapshot(), f"no {kind} report frame parsed by the SDK within {a.connect_wait} s")

    log("enable, servo mode, state 0")
    call("motion_enable(True)", arm.motion_enable(enable=True))
    call("set_mode(1)", arm.set_mode(1))
    call("set_state(0)", arm.set_state(0))
    time.sleep(0.5)  # let the 5 Hz rich stream show the new mode
    check(arm.mode == 1, f"the rich report shows mode {arm.mode} after set_mode(1), expected 1")
    check(arm.error_code == 0, f"controller error {arm.error_code} after the set-up")
    code, q0 = arm.get_servo_angle(is_radian=True)
    call("get_servo_angle (start)", code)
    q0 = list(q0[:6])
    summary["q0"] = q0

    log("streaming servo-j")
    cmds = []          # (time sent, 6 angles)
    polled = []        # (time read, 6 angles) from get_servo_angle
    servo_codes = {}
    period = 1.0 / RATE_HZ
    n = int(SECONDS * RATE_HZ)
    t0 = time.monotonic()
    for k in range(1, n + 1):
        ts = k * period
        q = [q0[i] + AMPL[i] * math.sin(2 * math.pi * FREQ[i] * ts) for i in range(6)]
        code = arm.set_servo_angle_j(q + [0.0], is_radian=True)
        now = time.monotonic()
        servo_codes[code] = servo_codes.get(code, 0) + 1
        cmds.append((now, q))
        code, qr = arm.get_servo_angle(is_radian=True)
        if code == 0:
            polled.append((time.monotonic(), list(qr[:6])))
        else:
            servo_codes[f"get_servo_angle={code}"] = servo_codes.get(f"get_servo_angle={code}", 0) + 1
        sleep = t0 + k * period - time.monotonic()
        if sleep > 0:
            time.sleep(sleep)
    t_end = time.monotonic()
    summary["servo_j_codes"] = {str(k): v for k, v in servo_codes.items()}
    bad = {k: v for k, v in servo_codes.items() if k != 0}
    check(not bad, f"set_servo_angle_j / get_servo_angle returned non-zero codes: {bad} of {n} calls")
    summary["stream_hz"] = round(n / (t_end - t0), 1)

    def tracked(name, samples):
        during = [s for s in samples if t0 <= s[0] <= t_end]
        err, lag = tracking(during, cmds, q0)
        summary[f"track_{name}"] = {"samples": len(during), "max_err_rad": round(err, 5), "lag_s": lag}
        check(len(during) >= 5, f"{name}: only {len(during)} samples during the motion")
        check(err <= TRACK_TOL,
              f"{name}: joint angles do not track the command within {TRACK_TOL} rad at any "
              f"lag <= {LAG_MAX} s (best max error {err:.4f} rad)")

    tracked("get_servo_angle", polled)
    for kind, rec in recs.items():
        tracked(f"{kind}_report", rec.snapshot())

    # Hold: servo mode keeps the last target.
    q_last = cmds[-1][1]
    time.sleep(0.5)
    code, qh = arm.get_servo_angle(is_radian=True)
    call("get_servo_angle (hold)", code)
    hold = max(abs(qh[i] - q_last[i]) for i in range(6))
    summary["hold_err_get_servo_angle_rad"] = round(hold, 6)
    check(hold <= HOLD_TOL, f"hold: get_servo_angle is {hold:.4f} rad from the last command (> {HOLD_TOL})")
    t_hold = time.monotonic()
    deadline = t_hold + 1.0
    while time.monotonic() < deadline and not [s for s in rich.snapshot() if s[0] > t_hold]:
        time.sleep(0.02)
    fresh = [s for s in rich.snapshot() if s[0] > t_hold]
    if check(fresh, "hold: no rich report within 1 s"):
        hr = max(abs(fresh[-1][1][i] - q_last[i]) for i in range(6))
        summary["hold_err_rich_report_rad"] = round(hr, 6)
        check(hr <= HOLD_TOL, f"hold: the rich report is {hr:.4f} rad from the last command (> {HOLD_TOL})")

    tau = arm.joints_torque
    summary["joints_torque"] = [round(x, 4) for x in tau]
    check(len(tau) == 7 and all(math.isfinite(x) for x in tau), f"joint torques {tau!r} are not 7 finite values")
    check(arm.error_code == 0 and arm.warn_code == 0,
          f"controller error/warning {arm.error_code}/{arm.warn_code} at the end")

    log("disconnecting")
    arm.disconnect()
    for w, _ in watchers.values():
        w.disconnect()
    faulthandler.cancel_dump_traceback_later()
    check(not arm.connected, "still connected after disconnect()")

    print("SUMMARY " + json.dumps(summary))
    if fails:
        for f in fails:
            print("FAIL: " + f)
        return 1
    print("OK: the xArm SDK session passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
