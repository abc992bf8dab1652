"""Fly a policy on a PX4 vehicle in OFFBOARD mode over MAVLink (MAVSDK-Python), with a watchdog.

:class:`FlightController` runs the mission: connect, wait for the vehicle's health (local position,
home, pre-arm), arm, take off, stream NED velocity setpoints from the
:class:`~safenav.deploy.runtime.OnboardRuntime` at a fixed rate in OFFBOARD, stop at the goal
(Hold) and land. The vehicle link is behind the small :class:`VehicleLink` interface;
:class:`MavsdkLink` implements it with MAVSDK's native binding (the ``mavsdk`` package, which
embeds MAVSDK's C++ core; no ``mavsdk_server`` process).

Watchdog, every control tick:

- **missed deadline**: the tick woke up more than a period late, or computing the setpoint took
  longer than ``deadline_fraction`` of the period -> that tick sends a zero-velocity setpoint;
- **stale or invalid perception / state**: the runtime's guards return hover -> zero velocity;
- **link loss**: no telemetry for ``link_timeout_s`` -> send zero velocity (best effort), stop and
  raise :class:`FlightAborted` (the CLI exits with status 3). PX4 itself fails over to Hold or
  Land when our setpoints stop for ``COM_OF_LOSS_T``;
- **mode change**: the vehicle leaves OFFBOARD (pilot or failsafe took over) -> abort, leaving the
  vehicle to whoever took it.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from safenav.deploy.frames import local_ned_to_world, ned_to_enu
from safenav.deploy.perception_link import PerceptionClient, PerceptionFrame
from safenav.deploy.runtime import OnboardRuntime
from safenav.errors import SafenavError

log = logging.getLogger("safenav.deploy.fly")


class FlightAborted(SafenavError):
    """The flight was stopped by the watchdog or the vehicle (link loss, refusal, timeout)."""


@dataclass
class Telemetry:
    position_ned: np.ndarray
    velocity_ned: np.ndarray
    stamp: float  # time.monotonic() when received


class VehicleLink(Protocol):
    """What the flight controller needs from a vehicle connection."""

    def connect(self, timeout_s: float) -> None: ...
    def wait_ready(self, timeout_s: float) -> None: ...
    def latest(self) -> Telemetry | None: ...
    def flight_mode(self) -> str: ...
    def in_air(self) -> bool: ...
    def arm(self) -> None: ...
    def takeoff(self, altitude_m: float) -> None: ...
    def start_offboard(self, yaw_deg: float) -> None: ...
    def send_velocity_ned(self, v_ned: np.ndarray, yaw_deg: float) -> None: ...
    def hold(self) -> None: ...
    def land(self) -> None: ...
    def close(self) -> None: ...


class MavsdkLink:
    """:class:`VehicleLink` over MAVSDK (``mavsdk`` >= 4, the native binding)."""

    def __init__(self, url: str) -> None:
        self.url = url
        self._latest: Telemetry | None = None
        self._mavsdk = None
        self._system = None

    def connect(self, timeout_s: float) -> None:
        from mavsdk import ComponentType, Configuration, Mavsdk, log_subscribe

        def route(level, message, file, line) -> bool:  # MAVSDK's own log -> logging
            logging.getLogger("safenav.mavsdk").log(
                {0: logging.DEBUG, 1: logging.DEBUG, 2: logging.INFO}.get(
                    int(level), logging.WARNING
                ),
                "%s",
                message,
            )
            return True

        log_subscribe(route)
        self._mavsdk = Mavsdk(
            Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
        )
        try:
            self._mavsdk.add_any_connection(self.url)
        except Exception as err:  # noqa: BLE001 -- MAVSDK raises its own types
            raise FlightAborted(f"cannot open MAVLink connection {self.url!r}: {err}") from None
        system = self._mavsdk.first_autopilot(timeout_s)
        if system is None:
            raise FlightAborted(f"no autopilot heartbeat on {self.url} within {timeout_s:.0f} s "
                                "(is the vehicle / `safenav sim-vehicle` running and sending there?)")  # fmt: skip
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.offboard import Offboard
        from mavsdk.plugins.telemetry import Telemetry as MavTelemetry

        self._system = system
        self.telemetry, self.action, self.offboard = (
            MavTelemetry(system),
            Action(system),
            Offboard(system),
        )

        def on_pv(pv, _user_data) -> None:
            p, v = pv.position, pv.velocity
            self._latest = Telemetry(np.array([p.north_m, p.east_m, p.down_m]),
                                     np.array([v.north_m_s, v.east_m_s, v.down_m_s]), time.monotonic())  # fmt: skip

        self.telemetry.subscribe_position_velocity_ned(on_pv)

    def wait_ready(self, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while True:
            h = self.telemetry.health()
            if (
                h.is_local_position_ok
                and h.is_home_position_ok
                and h.is_armable
                and self._latest is not None
            ):
                return
            if time.monotonic() > end:
                raise FlightAborted(f"vehicle not ready after {timeout_s:.0f} s: {h}")
            time.sleep(0.05)

    def latest(self) -> Telemetry | None:
        return self._latest

    def flight_mode(self) -> str:
        return self.telemetry.flight_mode().name

    def in_air(self) -> bool:
        return bool(self.telemetry.in_air())

    def _call(self, what: str, fn, *args) -> None:
        try:
            fn(*args)
        except Exception as err:  # noqa: BLE001 -- ActionError / OffboardError
            raise FlightAborted(f"vehicle refused {what}: {err}") from None

    def arm(self) -> None:
        self._call("arming", self.action.arm)

    def takeoff(self, altitude_m: float) -> None:
        try:
            self.action.set_takeoff_altitude(float(altitude_m))
        except Exception as err:  # noqa: BLE001 -- keep the vehicle's own MIS_TAKEOFF_ALT
            log.warning("could not set the takeoff altitude (%s); using the vehicle's", err)
        self._call("takeoff", self.action.takeoff)

    def start_offboard(self, yaw_deg: float) -> None:
        self.send_velocity_ned(np.zeros(3), yaw_deg)  # PX4 needs a setpoint stream first
        self._call("OFFBOARD", self.offboard.start)

    def send_velocity_ned(self, v_ned: np.ndarray, yaw_deg: float) -> None:
        from mavsdk.plugins.offboard import VelocityNedYaw

        self.offboard.set_velocity_ned(
            VelocityNedYaw(float(v_ned[0]), float(v_ned[1]), float(v_ned[2]), float(yaw_deg))
        )

    def hold(self) -> None:
        self._call("Hold", self.offboard.stop)

    def land(self) -> None:
        self._call("landing", self.action.land)

    def close(self) -> None:
        if self._mavsdk is not None:
            self._mavsdk.destroy()
            self._mavsdk = None


@dataclass
class FlyConfig:
    """Settings of a flight (``safenav fly``)."""

    goal: tuple[float, float, float]
    """Goal in the world frame (ENU, metres)."""
    rate_hz: float = 20.0
    """Setpoint rate (>= 10 Hz)."""
    takeoff_altitude: float = 1.5
    """Takeoff altitude above home, metres."""
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """World ENU position of PX4's local NED origin."""
    goal_tolerance: float = 0.5
    """The goal is reached within this distance (m)."""
    link_timeout_s: float = 1.0
    """No telemetry for this long = link lost."""
    deadline_fraction: float = 0.8
    """A setpoint computed in more than this fraction of the period is late: zero is sent."""
    connect_timeout_s: float = 15.0
    ready_timeout_s: float = 15.0
    takeoff_timeout_s: float = 20.0
    max_flight_s: float = 120.0
    """Abort (hold and land) if the goal is not reached within this many seconds of OFFBOARD."""
    land_timeout_s: float = 30.0
    land: bool = True
    """Land at the goal (else hold there)."""


@dataclass
class FlightLog:
    """What happened; the summary of ``safenav fly``."""

    reached_goal: bool = False
    aborted: str = ""
    flight_time_s: float = 0.0
    ticks: int = 0
    hover_ticks: int = 0
    late_ticks: int = 0
    shielded_ticks: int = 0
    filtered_ticks: int = 0
    min_goal_distance_m: float = math.inf
    setpoint_ms: list[float] = field(default_factory=list)
    trajectory: list[tuple[float, list[float]]] = field(default_factory=list)
    reasons: dict[str, int] = field(default_factory=dict)
    truth: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        ms = np.asarray(self.setpoint_ms) if self.setpoint_ms else np.zeros(1)
        return {
            "reached_goal": self.reached_goal, "aborted": self.aborted or None,
            "flight_time_s": round(self.flight_time_s, 3), "ticks": self.ticks,
            "hover_ticks": self.hover_ticks, "late_ticks": self.late_ticks,
            "shielded_ticks": self.shielded_ticks, "filtered_ticks": self.filtered_ticks,
            "min_goal_distance_m": round(self.min_goal_distance_m, 3) if math.isfinite(self.min_goal_distance_m) else None,
            "setpoint_p50_ms": round(float(np.percentile(ms, 50)), 3),
            "setpoint_p99_ms": round(float(np.percentile(ms, 99)), 3),
            "hover_reasons": self.reasons,
            # the simulator's ground truth, when the perception stream carries it (sim-vehicle);
            # None with real sensors
            "collisions": int(self.truth["collisions"]) if "collisions" in self.truth else None,
            "min_clearance_m": _rounded(self.truth.get("min_clearance")),
        }  # fmt: skip


def _rounded(x: Any, digits: int = 3) -> float | None:
    try:
        return round(float(x), digits) if math.isfinite(float(x)) else None
    except (TypeError, ValueError):
        return None


class FlightController:
    """Runs one flight of ``runtime``'s policy on ``link`` (see the module docstring)."""

    def __init__(self, runtime: OnboardRuntime, link: VehicleLink, config: FlyConfig,
                 perception: tuple[str, int] | None = None, recorder: Any = None) -> None:  # fmt: skip
        if not config.rate_hz >= 10.0:
            raise SafenavError(
                f"--rate {config.rate_hz} Hz is too low: PX4 offboard needs a steady stream, use >= 10 Hz"
            )
        for name in ("goal", "origin"):
            value = np.asarray(getattr(config, name), dtype=float)
            if value.shape != (3,) or not np.isfinite(value).all():
                raise SafenavError(f"--{name} {value.tolist()} is not three finite numbers")
        self.runtime, self.link, self.config = runtime, link, config
        self.perception_addr = perception
        self.recorder = recorder  # a McapRecorder (safenav.deploy.mcap_log) or None
        self.log = FlightLog()
        self._perception: PerceptionClient | None = None
        self._stop = threading.Event()
        self.snapshots: list[dict[str, Any]] = []  # simulator truth at <= 5 Hz (for rendering)
        self._last_snapshot = -math.inf
        self._last_heard = -math.inf  # stamp of the latest telemetry with a finite stamp
        self._movers: np.ndarray | None = None  # the latest tracker output, for the recorder

    # ------------------------------------------------------------------ helpers
    def _on_frame(self, frame: PerceptionFrame) -> None:
        self.runtime.update_frame(frame)
        if self.recorder is not None and frame.obstacles is not None:
            with contextlib.suppress(TypeError, ValueError):  # the runtime rejects it too
                self._movers = np.array([[*np.asarray(o.p, dtype=float).reshape(3), float(o.width),
                                          float(o.height), float(bool(o.cuboid if o.cuboid is not None
                                          else o.height < self.runtime.config.cuboid_below_height))]
                                         for o in frame.obstacles], dtype=float).reshape(-1, 6)  # fmt: skip
        if frame.truth:
            self.log.truth = frame.truth
            if frame.stamp - self._last_snapshot >= 0.2:
                self._last_snapshot = frame.stamp
                self.snapshots.append({"t": frame.stamp, **frame.truth})

    def _on_telemetry(self) -> Telemetry:
        tel = self.link.latest()
        now = time.monotonic()
        if tel is not None and math.isfinite(tel.stamp):  # a NaN / Inf stamp dates nothing
            self._last_heard = tel.stamp
        if tel is None or not now - self._last_heard <= self.config.link_timeout_s:
            age = "never" if tel is None else f"{now - self._last_heard:.2f} s ago"
            raise FlightAborted(f"link lost: last telemetry from the vehicle {age} "
                                f"(> {self.config.link_timeout_s:.1f} s); stopped. PX4 falls back to "
                                "Hold/Land after COM_OF_LOSS_T without setpoints")  # fmt: skip
        return tel

    def _feed_state(self, tel: Telemetry) -> None:
        pos = local_ned_to_world(tel.position_ned, self.config.origin)
        vel = local_ned_to_world(tel.velocity_ned, (0.0, 0.0, 0.0))
        self.runtime.update_state(pos, vel, tel.stamp)

    def _record(self, tel: Telemetry, now: float, setpoint_ned=None, sp=None) -> None:
        """Hand this tick to the recorder (``--record``): the vehicle's state, the setpoint sent
        (world ENU), the range image the policy saw and the tracked obstacles."""
        if self.recorder is None:
            return
        ranges = None
        if sp is not None and sp.observation is not None:  # lidar = (range - d) / range
            current = sp.observation["lidar"][
                : len(self.runtime.cfg.lidar_v_angles)
            ]  # no memory rows
            ranges = self.runtime.cfg.lidar_range * (1.0 - current)
        self.recorder.record(
            now, local_ned_to_world(tel.position_ned, self.config.origin),
            local_ned_to_world(tel.velocity_ned, (0.0, 0.0, 0.0)), self.runtime.goal_yaw,
            setpoint=None if setpoint_ned is None else ned_to_enu(setpoint_ned), ranges=ranges,
            movers=self._movers if sp is not None else None,
        )  # fmt: skip

    def _finite_telemetry(self, timeout_s: float) -> Telemetry:
        """The latest telemetry once its position and velocity are finite: a NaN or Inf sample is
        no home or start position (the link check runs meanwhile)."""
        end = time.monotonic() + timeout_s
        while True:
            tel = self._on_telemetry()
            if np.isfinite(tel.position_ned).all() and np.isfinite(tel.velocity_ned).all():
                return tel
            if time.monotonic() > end:
                raise FlightAborted(f"no finite vehicle position within {timeout_s:.0f} s")
            time.sleep(0.05)

    def _wait(self, what: str, cond, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while not cond():
            tel = self._on_telemetry()
            if np.isfinite(tel.position_ned).all():
                self._record(tel, time.monotonic())
            if time.monotonic() > end:
                raise FlightAborted(f"timed out after {timeout_s:.0f} s waiting for {what}")
            time.sleep(0.05)

    def stop(self) -> None:
        """Ask a running :meth:`fly` to stop (hold and land) at the next tick."""
        self._stop.set()

    # ------------------------------------------------------------------ the flight
    def fly(self) -> FlightLog:
        c = self.config
        try:
            if self.perception_addr is not None:
                self._perception = PerceptionClient(*self.perception_addr, on_frame=self._on_frame,
                                                    on_error=lambda m: log.warning("%s", m)).start()  # fmt: skip
            log.info("connecting to %s", getattr(self.link, "url", "the vehicle"))
            self.link.connect(c.connect_timeout_s)
            self.link.wait_ready(c.ready_timeout_s)
            tel = self._finite_telemetry(c.ready_timeout_s)
            log.info("vehicle ready; arming and taking off to %.1f m", c.takeoff_altitude)
            self.link.arm()
            self.link.takeoff(c.takeoff_altitude)
            home_down = tel.position_ned[2]
            self._wait("the takeoff altitude",
                       lambda: -(self._on_telemetry().position_ned[2] - home_down) >= c.takeoff_altitude - 0.15,
                       c.takeoff_timeout_s)  # fmt: skip
            tel = self._finite_telemetry(c.takeoff_timeout_s)
            self._feed_state(tel)
            start = local_ned_to_world(tel.position_ned, c.origin)
            self.runtime.set_goal(c.goal, start=start)
            if self.recorder is not None:
                self.recorder.update_scene(start=start, goal_yaw=self.runtime.goal_yaw)
            yaw = self.runtime.step().yaw_ned_deg
            self.link.start_offboard(yaw)
            log.info(
                "OFFBOARD: flying to %s at %.0f Hz", [round(float(x), 2) for x in c.goal], c.rate_hz
            )
            self._control_loop()
            self._finish()
        except FlightAborted as err:
            self.log.aborted = str(err)
            self._emergency_stop(str(err))
            raise
        except KeyboardInterrupt:
            self.log.aborted = "interrupted"
            self._emergency_stop("interrupted by the user")
            raise
        except Exception as err:  # a bug: still stop the vehicle before it propagates
            self.log.aborted = f"internal error: {err!r}"
            self._emergency_stop(self.log.aborted)
            raise
        finally:
            if self._perception is not None:
                self._perception.close()
        return self.log

    def _control_loop(self) -> None:
        c = self.config
        period = 1.0 / c.rate_hz
        t_start = time.monotonic()
        deadline = t_start
        while True:
            deadline += period
            sleep = deadline - time.monotonic()
            if sleep > 0:
                time.sleep(sleep)
            now = time.monotonic()
            late = now - deadline > period  # woke up more than a period late: a missed deadline
            if late:
                deadline = now  # resynchronise, do not burst
            tel = self._on_telemetry()
            self._feed_state(tel)
            t0 = time.perf_counter()
            sp = self.runtime.step(now)
            compute = time.perf_counter() - t0
            self.log.setpoint_ms.append(compute * 1e3)
            if compute > c.deadline_fraction * period:
                late = True
            if late or sp.hover:
                v, reason = np.zeros(3), ("missed control deadline" if late else sp.reason)
                self.log.late_ticks += int(late)
                self.log.hover_ticks += 1
                key = reason.split(":")[0]
                self.log.reasons[key] = self.log.reasons.get(key, 0) + 1
            else:
                v = sp.velocity_ned
                self.log.shielded_ticks += int(sp.shielded)
                self.log.filtered_ticks += int(sp.filtered)
            yaw = sp.yaw_ned_deg if math.isfinite(sp.yaw_ned_deg) else 0.0
            self.link.send_velocity_ned(v, yaw)
            self._record(tel, now, v, sp)
            self.log.ticks += 1
            self.log.flight_time_s = now - t_start
            pos = local_ned_to_world(tel.position_ned, c.origin)
            self.log.trajectory.append((round(now - t_start, 3), [round(float(x), 3) for x in pos]))
            dist = float(np.linalg.norm(np.asarray(c.goal) - pos))
            self.log.min_goal_distance_m = min(self.log.min_goal_distance_m, dist)
            if dist < c.goal_tolerance:
                self.log.reached_goal = True
                log.info("goal reached after %.1f s", now - t_start)
                return
            mode = self.link.flight_mode()
            if mode != "OFFBOARD" and now - t_start > 1.0:
                raise FlightAborted(
                    f"the vehicle left OFFBOARD (now {mode}): a pilot or failsafe took over"
                )
            if self._stop.is_set():
                raise FlightAborted("stopped on request")
            if now - t_start > c.max_flight_s:
                raise FlightAborted(f"goal not reached within {c.max_flight_s:.0f} s")

    def _finish(self) -> None:
        c = self.config
        self.link.send_velocity_ned(np.zeros(3), 0.0)
        self.link.hold()
        if not c.land:
            return
        self.link.land()
        self._wait("touchdown", lambda: not self.link.in_air(), c.land_timeout_s)
        log.info("landed")

    def _emergency_stop(self, reason: str) -> None:
        """Best effort, never blocking on the link: zero velocity (PX4 holds), then land if the
        link is still up."""
        log.error("stopping: %s", reason)
        with contextlib.suppress(Exception):
            self.link.send_velocity_ned(np.zeros(3), 0.0)
        tel = self.link.latest()
        if (
            tel is not None
            and time.monotonic() - tel.stamp < self.config.link_timeout_s
            and "left OFFBOARD" not in reason
        ):
            try:
                self.link.hold()
                if self.config.land:
                    self.link.land()
            except Exception:  # noqa: BLE001
                pass


__all__ = [
    "FlightAborted",
    "FlightController",
    "FlightLog",
    "FlyConfig",
    "MavsdkLink",
    "Telemetry",
    "VehicleLink",
]
