"""Closed loop on loopback: ``safenav sim-vehicle`` <-> ``safenav fly`` (MAVSDK, PX4 offboard).

Both run as subprocesses, exactly as a user runs them; every wait is bounded. The policy is the
scripted go-to-goal actor exported to ONNX, so no checkpoint is needed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from safenav.deploy.demo import free_port, sim_vehicle_command

pytest.importorskip("mavsdk")
pytest.importorskip("onnxruntime")

CLI = [sys.executable, "-c", "from safenav.cli import main; main()"]
START = (1.207, -9.0)  # test episode 0 of the easy world (seed 1)
GOAL = (1.2, -3.5, 1.5)  # ~5.5 m north, pillars on the way: the policy has to go round


@pytest.fixture(scope="module")
def policy(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("policy") / "policy.onnx"
    subprocess.run([*CLI, "export", "--scripted", "--preset", "easy", "--onnx", str(out)], check=True,
                   timeout=60, capture_output=True)  # fmt: skip
    return out


class Proc:
    """A subprocess whose stderr lines are collected in a thread (so pipes never fill up)."""

    def __init__(self, args: list[str]) -> None:
        self.p = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.err: list[str] = []
        self.out: list[str] = []
        self._t = [threading.Thread(target=self._pump, args=(s, buf), daemon=True)
                   for s, buf in ((self.p.stderr, self.err), (self.p.stdout, self.out))]  # fmt: skip
        for t in self._t:
            t.start()

    def _pump(self, stream, buf) -> None:
        for line in stream:
            buf.append(line)

    def wait_for(self, text: str, timeout: float) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if any(text in line for line in self.err + self.out):
                return True
            if self.p.poll() is not None:
                time.sleep(0.1)
                return any(text in line for line in self.err + self.out)
            time.sleep(0.02)
        return False

    def stop(self) -> None:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()


def start_vehicle(port: int, pport: int, *extra: str) -> Proc:
    sim = Proc(sim_vehicle_command(
        "--preset", "easy", "--start", str(START[0]), str(START[1]),
        "--connect", f"127.0.0.1:{port}", "--perception-port", str(pport),
        "--param", "MPC_LAND_SPEED=1.5", "COM_DISARM_LAND=0.5", *extra,
    ))  # fmt: skip
    assert sim.wait_for("sim-vehicle: PX4", 60), "".join(sim.err + sim.out)
    return sim


def fly_args(policy: Path, port: int, pport: int, *extra: str) -> list[str]:
    return [*CLI, "fly", "--policy", str(policy), "--connect", f"udpin://127.0.0.1:{port}",
            "--perception", f"127.0.0.1:{pport}", "--goal", *map(str, GOAL),
            "--takeoff-altitude", "1.5", "--max-flight-time", "40", *extra]  # fmt: skip


@pytest.mark.long
@pytest.mark.timeout(120)
def test_closed_loop_reaches_goal_and_lands(policy: Path, tmp_path: Path) -> None:
    port, pport = free_port(), free_port(socket_kind_tcp())
    sim = start_vehicle(port, pport)
    try:
        out = tmp_path / "flight.json"
        fly = subprocess.run(fly_args(policy, port, pport, "--shield", "--json", str(out)),
                             capture_output=True, text=True, timeout=90)  # fmt: skip
        summary = json.loads(out.read_text()) if out.exists() else {}
        assert fly.returncode == 0, f"{summary}\n{fly.stderr[-3000:]}\n{''.join(sim.err[-30:])}"
        assert summary["reached_goal"] is True
        assert summary["min_goal_distance_m"] <= 0.5  # < 0.5 m, rounded to mm in the summary
        # Watchdog statistics: the loop ran at its rate and computed setpoints in time.
        assert summary["ticks"] > 20
        assert summary["late_ticks"] <= 0.1 * summary["ticks"]
        assert "landed" in fly.stderr
    finally:
        sim.stop()
    # The vehicle's own account: it flew, landed, and hit nothing.
    final = "".join(sim.out)
    assert "collisions 0" in final, final
    assert any("mode OFFBOARD" in line for line in sim.err)
    assert any("landed" in line for line in sim.err)


@pytest.mark.timeout(90)
def test_killing_the_vehicle_mid_flight_exits_nonzero_within_2s(policy: Path) -> None:
    port, pport = free_port(), free_port(socket_kind_tcp())
    sim = start_vehicle(port, pport)
    fly = Proc(fly_args(policy, port, pport))
    try:
        assert fly.wait_for("OFFBOARD: flying", 60), "".join(fly.err)
        time.sleep(1.0)  # mid-flight
        assert fly.p.poll() is None
        sim.p.send_signal(signal.SIGKILL)
        t_kill = time.monotonic()
        rc = fly.p.wait(timeout=10)
        elapsed = time.monotonic() - t_kill
    finally:
        fly.stop()
        sim.stop()
    err = "".join(fly.err)
    assert rc == 3, err[-2000:]
    assert "link lost" in err
    assert elapsed < 2.0, f"fly took {elapsed:.2f} s to stop after the vehicle died"


def socket_kind_tcp() -> int:
    import socket

    return socket.SOCK_STREAM


# ---------------------------------------------------------------------- watchdog (no MAVLink)
class FakeLink:
    """A scripted vehicle: telemetry at a position, records every setpoint."""

    url = "fake://"

    def __init__(self, alive_for: float = 1e9) -> None:
        self.t0 = time.monotonic()
        self.alive_for = alive_for
        self.sent: list[np.ndarray] = []
        self.pos = np.array([0.0, 0.0, -1.5])  # NED
        self.mode = "HOLD"
        self.airborne = False

    def connect(self, timeout_s):
        pass

    def wait_ready(self, timeout_s):
        pass

    def latest(self):
        from safenav.deploy.fly import Telemetry

        now = time.monotonic()
        stamp = min(now, self.t0 + self.alive_for)
        return Telemetry(self.pos.copy(), np.zeros(3), stamp)

    def flight_mode(self):
        return self.mode

    def in_air(self):
        return self.airborne

    def arm(self):
        pass

    def takeoff(self, altitude_m):
        self.airborne = True

    def start_offboard(self, yaw_deg):
        self.mode = "OFFBOARD"

    def send_velocity_ned(self, v_ned, yaw_deg):
        self.sent.append(np.asarray(v_ned, dtype=float).copy())

    def hold(self):
        self.mode = "HOLD"

    def land(self):
        self.airborne = False

    def close(self):
        pass


def _controller(link, runtime_policy, perception_ok=True, max_flight_s=0.6, **rt_kwargs):
    from safenav.deploy.fly import FlightController, FlyConfig
    from safenav.deploy.runtime import OnboardRuntime, RuntimeConfig
    from safenav.envs.config import make_config

    cfg = make_config("easy")
    rt = OnboardRuntime(runtime_policy, cfg, RuntimeConfig(require_tracker=False, **rt_kwargs))
    if perception_ok:
        # Keep the map fresh from a thread, like the perception client does.
        stop = threading.Event()

        def feed():
            while not stop.is_set():
                rt.update_points(np.zeros((0, 3)))
                time.sleep(0.02)

        threading.Thread(target=feed, daemon=True).start()
    else:
        stop = None
    ctl = FlightController(rt, link, FlyConfig(goal=(20.0, 0.0, 1.5), rate_hz=20.0, takeoff_altitude=0.0,
                                               max_flight_s=max_flight_s, link_timeout_s=0.3))  # fmt: skip
    return ctl, stop


def _constant_policy(value):
    return lambda s, l, d: np.full((1, 3), value, dtype=np.float32)  # noqa: E741


def test_watchdog_stale_perception_sends_zero_velocity() -> None:
    from safenav.deploy.fly import FlightAborted

    link = FakeLink()
    ctl, _ = _controller(link, _constant_policy(1.0), perception_ok=False)
    with pytest.raises(FlightAborted, match="not reached"):
        ctl.fly()
    assert len(link.sent) > 5
    assert all(np.all(v == 0) for v in link.sent)  # never a non-zero setpoint without perception
    assert ctl.log.hover_ticks >= ctl.log.ticks - 1


def test_watchdog_flies_with_fresh_perception_and_clamps() -> None:
    from safenav.deploy.fly import FlightAborted

    link = FakeLink()
    ctl, stop = _controller(link, _constant_policy(5.0))  # out-of-range action: clamped to v_max
    try:
        with pytest.raises(FlightAborted, match="not reached"):
            ctl.fly()
    finally:
        stop.set()
    moving = [v for v in link.sent if np.any(v != 0)]
    assert len(moving) >= 5
    # Goal frame x = east here: action (1, 1, 1) * v_max = 2 m/s per axis -> NED (2, 2, -2).
    np.testing.assert_allclose(moving[-1], [2.0, 2.0, -2.0], atol=1e-5)


def test_watchdog_missed_deadline_sends_zero_velocity() -> None:
    from safenav.deploy.fly import FlightAborted

    def slow(s, l, d):  # noqa: E741 -- 60 ms > 0.8 x 50 ms period: too late to use
        time.sleep(0.06)
        return np.full((1, 3), 0.5, dtype=np.float32)

    link = FakeLink()
    ctl, stop = _controller(link, slow)
    try:
        with pytest.raises(FlightAborted):
            ctl.fly()
    finally:
        stop.set()
    assert ctl.log.late_ticks >= 3
    assert all(np.all(v == 0) for v in link.sent)


def test_watchdog_link_loss_aborts_promptly() -> None:
    from safenav.deploy.fly import FlightAborted

    link = FakeLink(alive_for=0.3)
    ctl, stop = _controller(link, _constant_policy(0.5), max_flight_s=10.0)
    t0 = time.monotonic()
    try:
        with pytest.raises(FlightAborted, match="link lost"):
            ctl.fly()
    finally:
        stop.set()
    assert time.monotonic() - t0 < 1.5
    assert np.all(link.sent[-1] == 0)  # the last word is a stop


def test_fly_rejects_low_rate_and_missing_policy(tmp_path: Path, policy: Path, capsys) -> None:
    from safenav.cli import main

    with pytest.raises(SystemExit) as e:
        main(["fly", "--policy", str(tmp_path / "nope.onnx"), "--goal", "1", "2", "3"])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        main(["fly", "--policy", str(policy), "--goal", "1", "2", "3", "--rate", "5"])
    assert e.value.code == 2
    assert ">= 10 Hz" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["fly", "--goal", "1", "2", "3"])
    assert e.value.code == 2


def test_demo_without_checkpoint_is_a_clear_error(tmp_path: Path, capsys) -> None:
    from safenav.cli import main

    with pytest.raises(SystemExit) as e:
        main(["fly", "--demo", "--checkpoint", str(tmp_path / "missing.pt")])
    assert e.value.code == 2
    assert "missing.pt not found" in capsys.readouterr().err


if os.environ.get("SAFENAV_SKIP_FLIGHT"):  # pragma: no cover
    pytestmark = pytest.mark.skip("SAFENAV_SKIP_FLIGHT set")
