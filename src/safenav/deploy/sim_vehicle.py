"""A simulated PX4 multicopter that speaks real MAVLink on loopback, driven by SafeNav-v1.

To a ground station or companion computer (MAVSDK, QGroundControl, pymavlink) it looks like PX4
SITL: it sends ``HEARTBEAT`` (autopilot PX4, PX4 custom modes), ``SYS_STATUS`` (sensor health and
the pre-arm bit MAVSDK's health checks read), ``GPS_RAW_INT``, ``GLOBAL_POSITION_INT``,
``HOME_POSITION``, ``LOCAL_POSITION_NED``, ``ATTITUDE``, ``EXTENDED_SYS_STATE`` (landed state) and
``AUTOPILOT_VERSION``; it answers ``COMMAND_LONG``/``COMMAND_INT`` with ``COMMAND_ACK`` (arm/disarm,
takeoff, land, set mode, set message interval, request message) and the parameter protocol
(``PARAM_REQUEST_READ``/``_LIST``, ``PARAM_SET`` -> ``PARAM_VALUE``); and it flies
``SET_POSITION_TARGET_LOCAL_NED`` velocity (or position) setpoints under PX4's offboard rules:
OFFBOARD is refused until setpoints stream in, and when they stop for ``COM_OF_LOSS_T`` seconds it
falls back to Hold or Land (``COM_OBL_RC_ACT`` 5 or 4). Malformed or unexpected messages are
counted and ignored.

The physics is SafeNav-v1's: the world of ``(preset, world_seed)`` (pillars and moving obstacles,
which move exactly as in the env), the UAV's velocity tracker, and the env's collision geometry
(collisions are counted, not fatal). Frames: the world is ENU; PX4's local NED frame has its origin
at the world origin (as with motion capture; see :mod:`safenav.deploy.frames`).

Perception for the onboard runtime is served on a TCP port of 127.0.0.1
(:mod:`safenav.deploy.perception_link`): depth images of a 360-degree rig of pinhole cameras
rendered from the world, and the moving obstacles near the vehicle as an ideal tracker sees them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import logging
import math
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from pymavlink.dialects.v20 import common as mavlink

from safenav.deploy import px4
from safenav.deploy.camera import PinholeCamera, render_depth, rig_poses
from safenav.deploy.frames import enu_to_ned, ned_to_enu
from safenav.deploy.perception_link import (
    DepthImage,
    PerceptionFrame,
    TrackedObstacle,
    encode_frame,
)
from safenav.envs.config import EnvConfig, make_config
from safenav.envs.dynamics import (
    move_obstacles,
    sample_obstacle_goals,
    sample_obstacle_speeds,
    velocity_tracker,
)
from safenav.envs.nav import fixed_scenario
from safenav.envs.sensors import moving_obstacle_clearance, pillar_clearance
from safenav.envs.world import (
    CUBOID_HEIGHT,
    CUBOID_Z_RANGE,
    CYLINDER_HEIGHT,
    border_clearance,
    generate_world,
)
from safenav.errors import SafenavError, SafenavRuntimeError

log = logging.getLogger("safenav.deploy.sim_vehicle")

# Where PX4 SITL's default home is (Zurich); the world origin maps to it.
HOME_LAT, HOME_LON, HOME_ALT = 47.397742, 8.545594, 488.0
EARTH_RADIUS = 6371000.0


def parse_hostport(
    text: str, default_host: str = "127.0.0.1", flag: str = "address"
) -> tuple[str, int]:
    """``"host:port"``, ``":port"``, ``"port"`` or ``"udp://host:port"`` -> ``(host, port)``;
    ``SafenavError`` for anything else (a port outside 0-65535 too)."""
    from safenav.common.checks import parse_hostport as checked

    return checked(text, flag, default_host)


def _bound(kind: int, address: tuple[str, int], flag: str, what: str) -> socket.socket:
    """A socket bound to ``address``; a port in use (or not ours to take) is a
    ``SafenavRuntimeError`` naming ``flag``, a host that is not an address a ``SafenavError``."""
    sock = socket.socket(socket.AF_INET, kind)
    try:
        if kind == socket.SOCK_STREAM:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
    except OSError as err:
        sock.close()
        host, port = address
        if err.errno in (errno.EADDRINUSE, errno.EACCES):
            why = "is already in use" if err.errno == errno.EADDRINUSE else "needs privileges"
            raise SafenavRuntimeError(f"{flag}: the {what} port {host}:{port} {why} (another "
                                      f"sim-vehicle or PX4 SITL?): pick another port, or 0 for "
                                      "any free one") from None  # fmt: skip
        raise SafenavError(f"{flag} {host}:{port}: cannot bind the {what} socket there "
                           f"({err.strerror or err})") from None  # fmt: skip
    except (OverflowError, TypeError) as err:  # a port outside 0-65535
        sock.close()
        raise SafenavError(f"{flag} {address}: {err}") from None
    return sock


class MovingObstacles:
    """The env's moving obstacles of one world, stepped at the env's control rate.

    Mirrors ``SafeNavVectorEnv``'s obstacle motion with the same pure functions and random
    streams, so the simulator's obstacles follow the env's trajectories (tested equal)."""

    def __init__(self, cfg: EnvConfig, world, world_seed: int) -> None:
        self.cfg = cfg
        self.seed = torch.tensor([world_seed], dtype=torch.int64)
        self.ids = torch.arange(cfg.num_dynamic)
        self.origin = torch.as_tensor(world.dyn_origin)[None]
        self.width = torch.as_tensor(world.dyn_width)
        self.is_cuboid = torch.as_tensor(world.dyn_is_cuboid)
        self.step_count = 0
        self.counter = torch.zeros(1, cfg.num_dynamic, dtype=torch.int64)
        self.pos = self.origin.clone()
        self.goal = self._goal(self.counter)
        self.vel = torch.zeros_like(self.pos)
        self.speed = sample_obstacle_speeds(self.seed[:, None], self.ids[None], torch.zeros((), dtype=torch.int64),
                                            *cfg.dyn_speed_range)  # fmt: skip

    def _goal(self, counter: torch.Tensor) -> torch.Tensor:
        cfg = self.cfg
        return sample_obstacle_goals(self.seed[:, None], self.ids[None], counter, self.origin, self.is_cuboid[None],
                                     cfg.dyn_local_range, cfg.mover_limit, CUBOID_Z_RANGE,
                                     CYLINDER_HEIGHT / 2)  # fmt: skip

    def step(self) -> None:
        cfg = self.cfg
        self.step_count += 1
        period = max(1, int(round(cfg.dyn_speed_period * cfg.control_hz)))
        if self.step_count % period == 0:
            self.speed = sample_obstacle_speeds(self.seed[:, None], self.ids[None],
                                                torch.tensor(self.step_count // period), *cfg.dyn_speed_range)  # fmt: skip
        arrived = (self.goal - self.pos).norm(dim=-1) < 0.5
        if bool(arrived.any()):
            self.counter += arrived.long()
            self.goal = torch.where(arrived[..., None], self._goal(self.counter), self.goal)
        self.pos, self.vel = move_obstacles(self.pos, self.goal, self.speed, cfg.dt)


@dataclass
class SimVehicleConfig:
    """Settings of the simulated vehicle (``safenav sim-vehicle``)."""

    preset: str = "easy"
    """SafeNav-v1 preset of the world (easy, medium, paper)."""
    world_seed: int = 1
    """World seed (1 = the fixed test environment, paper IV-B)."""
    density: float = 1.0
    """Fraction of the obstacles that are active."""
    start: tuple[float, float] | None = None
    """Start (x, y) on the ground in the world; None = the start of test episode ``episode``."""
    episode: int = 0
    """Test-scenario episode whose start is used when ``start`` is None."""
    connect: str = "127.0.0.1:14540"
    """Where the ground station / companion listens (PX4 SITL sends to port 14540)."""
    bind: str = "127.0.0.1:0"
    """Local UDP address of the vehicle (port 0: any free port)."""
    perception_port: int = 14660
    """TCP port on 127.0.0.1 serving perception frames (0: any free port; -1: off)."""
    perception_hz: float = 15.0
    """Perception frame rate."""
    physics_hz: float = 100.0
    """Physics / setpoint-handling rate."""
    cameras: int = 4
    """Depth cameras around the body (360 degrees)."""
    camera_width: int = 80
    camera_height: int = 60
    camera_hfov_deg: float = 90.0
    camera_range: float = 10.0
    tracker_range: float = 8.0
    """Moving obstacles within this horizontal distance are reported by the ideal tracker."""
    params: dict[str, float] = field(default_factory=dict)
    """PX4 parameter overrides (e.g. ``{"COM_OF_LOSS_T": 1.0}``)."""
    env_overrides: dict[str, Any] = field(default_factory=dict)
    """EnvConfig field overrides."""


@dataclass
class SimStats:
    collisions: int = 0
    collisions_static: int = 0
    collisions_dynamic: int = 0
    collisions_border: int = 0  # touching the arena's border wall (SafeNav-v1's closed arena)
    min_clearance: float = math.inf
    flight_time: float = 0.0
    path: list = field(default_factory=list)


class SimVehicle:
    """The vehicle simulator (see the module docstring). ``start()`` runs it in a thread;
    ``run()`` runs it in the calling thread until ``stop()``."""

    SYSID, COMPID = 1, 1  # PX4's system and autopilot component ids

    def __init__(self, config: SimVehicleConfig | None = None) -> None:
        self.config = c = config or SimVehicleConfig()
        self.env_cfg = make_config(c.preset, density=c.density, **c.env_overrides)
        cfg = self.env_cfg
        self.world = generate_world(cfg, c.world_seed)
        ns = cfg.active_static
        self.pillar_xy = torch.as_tensor(self.world.pillar_xy[:ns])
        self.pillar_half = torch.as_tensor(self.world.pillar_half[:ns])
        self.pillar_height = torch.as_tensor(self.world.pillar_height[:ns])
        self.box_lo = torch.cat(
            [self.pillar_xy - self.pillar_half[:, None], torch.zeros(ns, 1)], -1
        )
        self.box_hi = torch.cat(
            [self.pillar_xy + self.pillar_half[:, None], self.pillar_height[:, None]], -1
        )
        self.obstacles = MovingObstacles(cfg, self.world, c.world_seed)
        self.n_dynamic = cfg.active_dynamic
        if c.start is None:
            starts, goals = fixed_scenario(cfg, c.world_seed, c.episode + 1)
            self.scenario_goal = goals[c.episode].numpy().astype(float)
            start = starts[c.episode, :2].numpy().astype(float)
        else:
            self.scenario_goal = None
            start = np.asarray(c.start, dtype=float)
        self.params = {**px4.DEFAULT_PARAMS, **{k: float(v) for k, v in c.params.items()}}
        self.home = np.array([start[0], start[1], 0.0])
        self.pos = self.home.copy()
        self.vel = np.zeros(3)
        self.yaw = 0.0  # ENU yaw of the body
        self.yaw_target: float | None = None
        self.acc = np.zeros(3)
        self.armed = False
        self.main_mode, self.sub_mode = int(px4.MainMode.AUTO), int(px4.AutoSubMode.LOITER)
        self.landed = True
        self.landed_state = mavlink.MAV_LANDED_STATE_ON_GROUND
        self.takeoff_target = 0.0
        self.hold_pos = self.pos.copy()
        self.setpoint_vel: np.ndarray | None = None
        self.setpoint_pos: np.ndarray | None = None
        self.setpoint_time = -math.inf
        self.armed_time = -math.inf
        self.touchdown_time = -math.inf
        self.sim_time = 0.0
        self.boot = time.monotonic()
        self.stats = SimStats()
        self._in_contact = False
        self._obstacle_accum = 0.0
        self.bad_messages = 0
        self.unexpected_messages = 0
        self.messages_received = 0
        self.gcs_addr: tuple[str, int] | None = None
        self.events: list[str] = []
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.camera = PinholeCamera.from_fov(
            c.camera_width, c.camera_height, c.camera_hfov_deg, c.camera_range
        )

        self.mav = mavlink.MAVLink(None, srcSystem=self.SYSID, srcComponent=self.COMPID)
        self.target = parse_hostport(c.connect)
        self.udp: socket.socket | None = None
        self.tcp: socket.socket | None = None
        self.perception_address: tuple[str, int] | None = None
        try:
            self.udp = _bound(socket.SOCK_DGRAM, parse_hostport(c.bind), "--bind", "MAVLink (UDP)")
            self.udp.setblocking(False)
            self.mavlink_address = self.udp.getsockname()
            if c.perception_port >= 0:
                self.tcp = _bound(socket.SOCK_STREAM, ("127.0.0.1", c.perception_port),
                                  "--perception-port", "perception (TCP)")  # fmt: skip
                self.tcp.listen(4)
                self.tcp.setblocking(False)
                self.perception_address = self.tcp.getsockname()
        except BaseException:
            self.close()  # the socket bound before the one that failed
            raise

    # ------------------------------------------------------------------ life cycle
    def start(self) -> SimVehicle:
        self._thread = threading.Thread(target=self.run, name="sim-vehicle", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self.close()

    def close(self) -> None:
        for sock in (self.udp, self.tcp):
            if sock is not None:
                with contextlib.suppress(OSError):
                    sock.close()

    @property
    def mode_name(self) -> str:
        return px4.MODE_NAMES.get((self.main_mode, self.sub_mode if self.main_mode == px4.MainMode.AUTO else 0),
                                  f"{self.main_mode}/{self.sub_mode}")  # fmt: skip

    def _event(self, text: str) -> None:
        log.info("%s", text)
        self.events.append(f"{self.sim_time:7.2f} {text}")

    def run(self, duration: float | None = None) -> None:
        """Run in real time until :meth:`stop` (or ``duration`` seconds)."""
        c = self.config
        sel = selectors.DefaultSelector()
        sel.register(self.udp, selectors.EVENT_READ, "udp")
        perception = None
        if self.tcp is not None:  # its own thread: rendering must never stall the autopilot
            perception = threading.Thread(
                target=self._perception_loop, name="sim-perception", daemon=True
            )
            perception.start()
        dt = 1.0 / c.physics_hz
        t0 = time.monotonic()
        next_phys = t0
        rates = {"heartbeat": 1.0, "sys_status": 2.0, "ext_sys_state": 5.0, "local_pos": 50.0,
                 "attitude": 50.0, "global_pos": 20.0, "gps": 5.0, "home": 0.5}  # fmt: skip
        next_send = dict.fromkeys(rates, t0)
        end = math.inf if duration is None else t0 + duration
        try:
            while not self._stop.is_set() and time.monotonic() < end:
                now = time.monotonic()
                timeout = max(0.0, min(next_phys, *next_send.values()) - now)
                if sel.select(timeout=min(timeout, 0.05)):
                    self._receive()
                now = time.monotonic()
                steps = 0
                while now >= next_phys and steps < 10:
                    with self._lock:
                        self._physics(dt)
                    next_phys += dt
                    steps += 1
                if now - next_phys > 0.5:  # far behind (machine stalled): resynchronise
                    next_phys = now
                for name, rate in rates.items():
                    if now >= next_send[name]:
                        self._send_telemetry(name)
                        next_send[name] = max(next_send[name] + 1.0 / rate, now)
        finally:
            self._stop.set()
            sel.close()
            if perception is not None:
                perception.join(timeout=2.0)

    # ------------------------------------------------------------------ MAVLink I/O
    def _send(self, msg) -> None:
        try:
            buf = msg.pack(self.mav)
            self.udp.sendto(buf, self.target)
            if self.gcs_addr is not None and self.gcs_addr != self.target:
                self.udp.sendto(buf, self.gcs_addr)
        except OSError:
            pass  # nobody listening yet (ICMP port unreachable): like a radio link

    def _receive(self) -> None:
        while True:
            try:
                data, addr = self.udp.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # e.g. ECONNREFUSED reported for an earlier send
            parser = mavlink.MAVLink(None)
            parser.robust_parsing = True
            try:
                msgs = parser.parse_buffer(data) or []
            except Exception:  # noqa: BLE001 -- anything malformed is dropped
                self.bad_messages += 1
                continue
            for msg in msgs:
                if msg.get_type() == "BAD_DATA":
                    self.bad_messages += 1
                    continue
                if msg.get_srcSystem() == self.SYSID and msg.get_srcComponent() == self.COMPID:
                    continue  # our own echo
                self.messages_received += 1
                if self.gcs_addr != addr and msg.get_type() == "HEARTBEAT":
                    self.gcs_addr = addr
                try:
                    with self._lock:
                        self._handle(msg)
                except Exception as err:  # noqa: BLE001 -- never let a message crash the vehicle
                    self.bad_messages += 1
                    log.debug("dropped %s: %s", msg.get_type(), err)

    def _handle(self, msg) -> None:
        kind = msg.get_type()
        if kind in ("HEARTBEAT", "TIMESYNC", "SYSTEM_TIME"):
            return
        target = getattr(msg, "target_system", 0)
        if target not in (0, self.SYSID):
            return
        if kind == "SET_POSITION_TARGET_LOCAL_NED":
            self._setpoint(msg)
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            if getattr(msg, "target_component", 0) not in (0, self.COMPID):
                return
            self._command(msg)
        elif kind == "PARAM_REQUEST_LIST":
            for i, name in enumerate(self.params):
                self._param_value(name, i)
        elif kind == "PARAM_REQUEST_READ":
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else ""
            names = list(self.params)
            if name in self.params:
                self._param_value(name, names.index(name))
            elif 0 <= msg.param_index < len(names):
                self._param_value(names[msg.param_index], msg.param_index)
        elif kind == "PARAM_SET":
            name = msg.param_id.rstrip("\x00")
            if name in self.params and math.isfinite(msg.param_value):
                self.params[name] = float(msg.param_value)
                self._event(f"param {name} = {msg.param_value:g}")
            if name in self.params:
                self._param_value(name, list(self.params).index(name))
        else:
            self.unexpected_messages += 1

    def _param_value(self, name: str, index: int) -> None:
        self._send(mavlink.MAVLink_param_value_message(
            name.encode(), float(self.params[name]), mavlink.MAV_PARAM_TYPE_REAL32, len(self.params), index))  # fmt: skip

    def _ack(self, msg, result: int) -> None:
        self._send(mavlink.MAVLink_command_ack_message(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))  # fmt: skip

    def _setpoint(self, msg) -> None:
        if msg.coordinate_frame not in (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_NED):
            self.unexpected_messages += 1
            return
        mask = msg.type_mask
        use_pos = not (mask & 0b111)
        use_vel = not (mask & 0b111000)
        pos = np.array([msg.x, msg.y, msg.z], dtype=float)
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        if use_pos and not np.isfinite(pos).all():
            use_pos = False
        if use_vel and not np.isfinite(vel).all():
            use_vel = False
        if not (use_pos or use_vel):
            self.unexpected_messages += 1  # nothing usable: not a setpoint (and it does not count)
            return
        if msg.coordinate_frame == mavlink.MAV_FRAME_BODY_NED:
            # Body-frame velocity (x forward, y right, z down) -> local NED, by the heading.
            psi = math.pi / 2 - self.yaw
            c, s = math.cos(psi), math.sin(psi)
            vel = np.array([c * vel[0] - s * vel[1], s * vel[0] + c * vel[1], vel[2]])
            use_pos = False
        self.setpoint_vel = ned_to_enu(vel) if use_vel else None
        self.setpoint_pos = ned_to_enu(pos) if use_pos else None
        if not (mask & (1 << 10)) and math.isfinite(msg.yaw):
            self.yaw_target = math.pi / 2 - msg.yaw  # NED yaw -> ENU yaw
        self.setpoint_time = time.monotonic()

    def _offboard_signal(self) -> bool:
        """Setpoints arrived within COM_OF_LOSS_T (wall clock, as on the real autopilot)."""
        return time.monotonic() - self.setpoint_time <= self.params["COM_OF_LOSS_T"]

    def _set_mode(self, main: int, sub: int) -> int:
        if main == px4.MainMode.OFFBOARD:
            if not self._offboard_signal():
                self._event("OFFBOARD refused: no setpoint stream")
                return mavlink.MAV_RESULT_DENIED
            self.main_mode, self.sub_mode = main, 0
        elif main == px4.MainMode.AUTO and sub == px4.AutoSubMode.LOITER:
            self.main_mode, self.sub_mode = main, sub
            self.hold_pos = self.pos.copy()
        elif main == px4.MainMode.AUTO and sub == px4.AutoSubMode.LAND:
            if self.landed:
                return mavlink.MAV_RESULT_DENIED
            self.main_mode, self.sub_mode = main, sub
            self.hold_pos = self.pos.copy()
        elif main == px4.MainMode.AUTO and sub == px4.AutoSubMode.TAKEOFF:
            return self._takeoff(math.nan)
        elif main in (px4.MainMode.POSCTL, px4.MainMode.ALTCTL):
            self.main_mode, self.sub_mode = main, 0
            self.hold_pos = self.pos.copy()
        else:
            return mavlink.MAV_RESULT_DENIED
        self._event(f"mode {self.mode_name}")
        return mavlink.MAV_RESULT_ACCEPTED

    def _takeoff(self, altitude: float) -> int:
        if not self.armed or not self.landed:
            return mavlink.MAV_RESULT_DENIED
        rel = self.params["MIS_TAKEOFF_ALT"] if not math.isfinite(altitude) else altitude - HOME_ALT
        self.takeoff_target = self.home[2] + max(0.5, rel)
        self.main_mode, self.sub_mode = int(px4.MainMode.AUTO), int(px4.AutoSubMode.TAKEOFF)
        self.hold_pos = self.pos.copy()
        self.landed = False
        self.landed_state = mavlink.MAV_LANDED_STATE_TAKEOFF
        self._event(f"takeoff to {self.takeoff_target:.2f} m")
        return mavlink.MAV_RESULT_ACCEPTED

    def _command(self, msg) -> None:
        cmd = msg.command
        p = [msg.param1, msg.param2, msg.param3, msg.param4]
        M = mavlink
        if cmd == M.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] == 1.0:
                if self.armed:
                    result = M.MAV_RESULT_ACCEPTED
                elif not self.landed:
                    result = M.MAV_RESULT_DENIED
                else:
                    self.armed, self.armed_time = True, self.sim_time
                    self._event("armed")
                    result = M.MAV_RESULT_ACCEPTED
            elif p[0] == 0.0:
                if self.landed or p[1] == 21196.0:
                    if self.armed:
                        self._event("disarmed")
                    self.armed = False
                    result = M.MAV_RESULT_ACCEPTED
                else:
                    result = M.MAV_RESULT_DENIED
            else:
                result = M.MAV_RESULT_DENIED
        elif cmd == M.MAV_CMD_NAV_TAKEOFF:
            alt = msg.param7 if msg.get_type() == "COMMAND_LONG" else msg.z
            result = self._takeoff(float(alt))
        elif cmd == M.MAV_CMD_NAV_LAND:
            result = self._set_mode(px4.MainMode.AUTO, px4.AutoSubMode.LAND)
        elif cmd == M.MAV_CMD_DO_SET_MODE:
            if not int(p[0]) & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                result = M.MAV_RESULT_DENIED
            else:
                result = self._set_mode(int(p[1]), int(p[2]))
        elif cmd == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = M.MAV_RESULT_ACCEPTED
        elif cmd in (
            M.MAV_CMD_REQUEST_MESSAGE,
            M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
            M.MAV_CMD_GET_HOME_POSITION,
        ):
            wanted = {M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: M.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                      M.MAV_CMD_GET_HOME_POSITION: M.MAVLINK_MSG_ID_HOME_POSITION}.get(cmd, int(p[0]))  # fmt: skip
            senders = {M.MAVLINK_MSG_ID_AUTOPILOT_VERSION: "autopilot_version",
                       M.MAVLINK_MSG_ID_HOME_POSITION: "home", M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: "ext_sys_state",
                       M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "global_pos", M.MAVLINK_MSG_ID_SYS_STATUS: "sys_status",
                       M.MAVLINK_MSG_ID_GPS_RAW_INT: "gps", M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: "local_pos",
                       M.MAVLINK_MSG_ID_ATTITUDE: "attitude"}  # fmt: skip
            if wanted in senders:
                self._ack(msg, M.MAV_RESULT_ACCEPTED)
                self._send_telemetry(senders[wanted])
                return
            result = M.MAV_RESULT_UNSUPPORTED
        else:
            result = M.MAV_RESULT_UNSUPPORTED
        self._ack(msg, result)

    # ------------------------------------------------------------------ telemetry
    def _boot_ms(self) -> int:
        return int((time.monotonic() - self.boot) * 1000) & 0xFFFFFFFF

    def _latlon(self, p: np.ndarray) -> tuple[int, int, float]:
        lat = HOME_LAT + math.degrees(p[1] / EARTH_RADIUS)
        lon = HOME_LON + math.degrees(p[0] / (EARTH_RADIUS * math.cos(math.radians(HOME_LAT))))
        return int(round(lat * 1e7)), int(round(lon * 1e7)), HOME_ALT + p[2]

    def _send_telemetry(self, name: str) -> None:
        M = mavlink
        with self._lock:
            pos, vel, yaw = self.pos.copy(), self.vel.copy(), self.yaw
        ned, vned = enu_to_ned(pos), enu_to_ned(vel)
        yaw_ned = math.remainder(math.pi / 2 - yaw, 2 * math.pi)
        if name == "heartbeat":
            base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            if self.armed:
                base |= M.MAV_MODE_FLAG_SAFETY_ARMED
            if self.main_mode in (px4.MainMode.AUTO, px4.MainMode.OFFBOARD):
                base |= (
                    M.MAV_MODE_FLAG_AUTO_ENABLED
                    | M.MAV_MODE_FLAG_GUIDED_ENABLED
                    | M.MAV_MODE_FLAG_STABILIZE_ENABLED
                )
            state = M.MAV_STATE_ACTIVE if self.armed else M.MAV_STATE_STANDBY
            self._send(M.MAVLink_heartbeat_message(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, base,
                                                   px4.encode_custom_mode(self.main_mode, self.sub_mode), state, 3))  # fmt: skip
        elif name == "sys_status":
            sensors = (M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL | M.MAV_SYS_STATUS_SENSOR_3D_MAG
                       | M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | M.MAV_SYS_STATUS_SENSOR_GPS
                       | M.MAV_SYS_STATUS_AHRS | M.MAV_SYS_STATUS_PREARM_CHECK)  # fmt: skip
            self._send(
                M.MAVLink_sys_status_message(
                    sensors, sensors, sensors, 200, 12600, -1, 90, 0, 0, 0, 0, 0, 0
                )
            )
        elif name == "ext_sys_state":
            self._send(
                M.MAVLink_extended_sys_state_message(M.MAV_VTOL_STATE_UNDEFINED, self.landed_state)
            )
        elif name == "local_pos":
            self._send(
                M.MAVLink_local_position_ned_message(self._boot_ms(), *ned.tolist(), *vned.tolist())
            )
        elif name == "attitude":
            # Tilt that produces the horizontal acceleration (small-angle multicopter model).
            fwd = self.acc[0] * math.cos(yaw) + self.acc[1] * math.sin(yaw)
            left = -self.acc[0] * math.sin(yaw) + self.acc[1] * math.cos(yaw)
            pitch, roll = -math.atan2(fwd, 9.81), -math.atan2(left, 9.81)
            self._send(
                M.MAVLink_attitude_message(self._boot_ms(), roll, pitch, yaw_ned, 0.0, 0.0, 0.0)
            )
        elif name == "global_pos":
            lat, lon, alt = self._latlon(pos)
            hdg = int(math.degrees(yaw_ned) % 360 * 100)
            self._send(M.MAVLink_global_position_int_message(
                self._boot_ms(), lat, lon, int(alt * 1000), int(pos[2] * 1000),
                *(int(round(x * 100)) for x in vned), hdg))  # fmt: skip
        elif name == "gps":
            lat, lon, alt = self._latlon(pos)
            speed = int(np.linalg.norm(vel[:2]) * 100)
            self._send(M.MAVLink_gps_raw_int_message(int((time.monotonic() - self.boot) * 1e6), M.GPS_FIX_TYPE_3D_FIX,
                                                     lat, lon, int(alt * 1000), 80, 120, speed, 0, 14))  # fmt: skip
        elif name == "home":
            lat, lon, alt = self._latlon(self.home)
            hned = enu_to_ned(self.home)
            self._send(M.MAVLink_home_position_message(lat, lon, int(alt * 1000), *hned.tolist(), [1.0, 0.0, 0.0, 0.0],
                                                       0.0, 0.0, 0.0))  # fmt: skip
        elif name == "autopilot_version":
            caps = (M.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                    | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                    | M.MAV_PROTOCOL_CAPABILITY_MISSION_INT)  # fmt: skip
            self._send(M.MAVLink_autopilot_version_message(caps, 0x010F0000, 0, 0, 0, b"\0" * 8, b"\0" * 8, b"\0" * 8,
                                                           0, 0, 0x5AFE))  # fmt: skip

    # ------------------------------------------------------------------ physics
    def _physics(self, dt: float) -> None:
        cfg, P = self.env_cfg, self.params
        self.sim_time += dt
        t = self.sim_time
        self._obstacle_accum += dt
        while self._obstacle_accum >= cfg.dt - 1e-9:
            self._obstacle_accum -= cfg.dt
            self.obstacles.step()
        cmd = np.zeros(3)
        if self.armed and not self.landed:
            main, sub = self.main_mode, self.sub_mode
            if main == px4.MainMode.OFFBOARD and not self._offboard_signal():
                act = int(P["COM_OBL_RC_ACT"])
                self._event(f"offboard setpoints lost for > {P['COM_OF_LOSS_T']:g} s: failsafe "
                            f"{'LAND' if act == px4.OBL_ACT_LAND else 'HOLD'}")  # fmt: skip
                self.main_mode, self.sub_mode = (
                    int(px4.MainMode.AUTO),
                    int(
                        px4.AutoSubMode.LAND if act == px4.OBL_ACT_LAND else px4.AutoSubMode.LOITER
                    ),
                )
                self.hold_pos = self.pos.copy()
                main, sub = self.main_mode, self.sub_mode
            if main == px4.MainMode.OFFBOARD:
                if self.setpoint_pos is not None:
                    cmd = (self.setpoint_pos - self.pos) * 1.0
                    if self.setpoint_vel is not None:
                        cmd = cmd + self.setpoint_vel
                elif self.setpoint_vel is not None:
                    cmd = self.setpoint_vel.copy()
            elif main == px4.MainMode.AUTO and sub == px4.AutoSubMode.TAKEOFF:
                cmd = self._hold_xy()
                cmd[2] = min(P["MPC_TKO_SPEED"], 1.5 * (self.takeoff_target - self.pos[2]) + 0.2)
                if self.pos[2] >= self.takeoff_target - 0.05:
                    self.main_mode, self.sub_mode = (
                        int(px4.MainMode.AUTO),
                        int(px4.AutoSubMode.LOITER),
                    )
                    self.hold_pos = np.array([*self.hold_pos[:2], self.takeoff_target])
                    self.landed_state = mavlink.MAV_LANDED_STATE_IN_AIR
                    self._event("takeoff complete: HOLD")
            elif main == px4.MainMode.AUTO and sub == px4.AutoSubMode.LAND:
                cmd = self._hold_xy()
                cmd[2] = -P["MPC_LAND_SPEED"]
                self.landed_state = mavlink.MAV_LANDED_STATE_LANDING
            else:  # HOLD, POSCTL, ...: hold the position
                cmd = (self.hold_pos - self.pos) * 1.0
        # PX4's velocity limits (a negative one, e.g. from a PARAM_SET, counts as 0).
        xy_max = max(P["MPC_XY_VEL_MAX"], 0.0)
        h = np.linalg.norm(cmd[:2])
        if h > xy_max:
            cmd[:2] *= xy_max / h
        z_dn, z_up = max(P["MPC_Z_VEL_MAX_DN"], 0.0), max(P["MPC_Z_VEL_MAX_UP"], 0.0)
        cmd[2] = float(np.clip(cmd[2], -z_dn, z_up))
        old_vel = self.vel
        if self.armed and not self.landed:
            p, v = velocity_tracker(torch.tensor(self.pos[None]), torch.tensor(self.vel[None]), torch.tensor(cmd[None]),
                                    dt, 1, cfg.velocity_time_constant, cfg.max_acceleration)  # fmt: skip
            self.pos, self.vel = p[0].numpy(), v[0].numpy()
            if self.yaw_target is not None:  # yaw toward the setpoint heading at <= 90 deg/s
                err = math.remainder(self.yaw_target - self.yaw, 2 * math.pi)
                self.yaw += float(np.clip(err, -math.pi / 2 * dt, math.pi / 2 * dt))
            if self.pos[2] <= 0.0:  # touchdown
                self.pos[2], self.vel = 0.0, np.zeros(3)
                if self.main_mode != px4.MainMode.AUTO or self.sub_mode != px4.AutoSubMode.TAKEOFF:
                    self.landed = True
                    self.landed_state = mavlink.MAV_LANDED_STATE_ON_GROUND
                    self.touchdown_time = t
                    self.main_mode, self.sub_mode = (
                        int(px4.MainMode.AUTO),
                        int(px4.AutoSubMode.LOITER),
                    )
                    self.hold_pos = self.pos.copy()
                    self._event("landed")
            self.stats.flight_time += dt
        else:
            self.vel = np.zeros(3)
        self.acc = (self.vel - old_vel) / dt
        # Auto-disarm (COM_DISARM_LAND after landing, COM_DISARM_PRFLT when never took off).
        if self.armed and self.landed:
            since = t - max(self.touchdown_time, self.armed_time)
            limit = (
                P["COM_DISARM_LAND"]
                if self.touchdown_time > self.armed_time
                else P["COM_DISARM_PRFLT"]
            )
            if 0 <= limit < since:
                self.armed = False
                self._event("auto-disarmed")
        self._check_collision()

    def _hold_xy(self) -> np.ndarray:
        cmd = (self.hold_pos - self.pos) * 1.0
        cmd[2] = 0.0
        return cmd

    def clearance(self) -> tuple[float, float, float]:
        """Distance from the UAV centre to the nearest pillar and moving obstacle surfaces and
        (horizontally) to the arena's border wall."""
        pos = torch.tensor(self.pos, dtype=torch.float32)[None]
        static = float(
            pillar_clearance(pos, self.pillar_xy, self.pillar_half, self.pillar_height)[0]
        )
        nd = self.n_dynamic
        dyn = math.inf
        if nd:
            rel = self.obstacles.pos[:, :nd] - pos[:, None]
            dyn = float(moving_obstacle_clearance(rel, self.obstacles.width[None, :nd], self.obstacles.is_cuboid[None, :nd],
                                                  pos[:, 2], CUBOID_HEIGHT, CYLINDER_HEIGHT).amin())  # fmt: skip
        return static, dyn, float(border_clearance(pos[0], self.env_cfg.half))

    def _check_collision(self) -> None:
        if self.landed:
            self._in_contact = False
            return
        static, dyn, border = self.clearance()
        clear = min(static, dyn, border) - self.env_cfg.uav_radius
        self.stats.min_clearance = min(self.stats.min_clearance, clear)
        contact = clear <= 0.0
        if contact and not self._in_contact:
            self.stats.collisions += 1
            what = min((static, "pillar"), (dyn, "moving obstacle"), (border, "border wall"))[1]
            if what == "pillar":
                self.stats.collisions_static += 1
            elif what == "moving obstacle":
                self.stats.collisions_dynamic += 1
            else:
                self.stats.collisions_border += 1
            self._event(f"COLLISION with the {what}")
        self._in_contact = contact

    # ------------------------------------------------------------------ perception
    def perception_frame(self) -> PerceptionFrame:
        """Depth images of the rig and the tracked obstacles, now."""
        with self._lock:
            pos, yaw = self.pos.copy(), self.yaw
            opos = self.obstacles.pos[0, : self.n_dynamic].clone()
            ovel = self.obstacles.vel[0, : self.n_dynamic].clone()
            stats = dataclasses.replace(self.stats, path=[])
            in_contact = self._in_contact
            mode, armed = self.mode_name, self.armed
        width = self.obstacles.width[: self.n_dynamic]
        cuboid = self.obstacles.is_cuboid[: self.n_dynamic]
        height = torch.where(cuboid, CUBOID_HEIGHT, CYLINDER_HEIGHT)
        half = torch.stack([width / 2, width / 2, height / 2], -1)
        # Every box the cameras can see: pillars, and moving obstacles by their bounding boxes.
        lo = torch.cat([self.box_lo, opos - half])
        hi = torch.cat([self.box_hi, opos + half])
        here = torch.tensor(pos, dtype=torch.float32)
        rel = (lo[:, :2] + hi[:, :2]) / 2 - here[:2]
        dist = rel.norm(dim=-1)
        radius = ((hi[:, :2] - lo[:, :2]) / 2).norm(dim=-1)
        bearing = torch.atan2(rel[:, 1], rel[:, 0])
        reach = dist - radius < self.config.camera_range
        cam = self.camera
        half_fov = math.atan((cam.width / 2) / cam.fx)
        images = []
        for i, (R, t) in enumerate(rig_poses(pos, yaw, self.config.cameras)):
            # Frustum culling: boxes whose bounding circle overlaps this camera's horizontal sector.
            axis = yaw + 2 * math.pi * i / self.config.cameras
            off = torch.remainder(bearing - axis + math.pi, 2 * math.pi) - math.pi
            spread = torch.asin((radius / dist.clamp(min=1e-3)).clamp(max=1.0))
            keep = reach & ((off.abs() <= half_fov + spread + 0.02) | (dist <= radius + 0.5))
            depth = render_depth(cam, R, t, lo[keep], hi[keep])
            images.append(DepthImage(depth, cam.fx, cam.fy, cam.cx, cam.cy, R, t))
        horiz = (opos[:, :2] - here[:2]).norm(dim=-1)
        tracked = [
            TrackedObstacle(opos[i].numpy().astype(float), ovel[i].numpy().astype(float),
                            float(width[i]), float(height[i]), bool(cuboid[i]))
            for i in torch.nonzero(horiz < self.config.tracker_range).squeeze(1).tolist()
        ]  # fmt: skip
        truth = {"pos": pos.tolist(), "collisions": stats.collisions,
                 "collisions_static": stats.collisions_static, "collisions_dynamic": stats.collisions_dynamic,
                 "collisions_border": stats.collisions_border,
                 "min_clearance": stats.min_clearance,
                 "flight_time": stats.flight_time, "in_contact": in_contact, "mode": mode, "armed": armed,
                 "dyn_pos": opos[:, :2].numpy().round(3).tolist(), "world_seed": self.config.world_seed,
                 "preset": self.config.preset}  # fmt: skip
        return PerceptionFrame(stamp=time.monotonic(), depth=images, obstacles=tracked, truth=truth)

    def _perception_loop(self) -> None:
        """Serve perception frames to every connected client at ``perception_hz``; a client that
        cannot take a frame within a period is dropped (it reconnects)."""
        period = 1.0 / self.config.perception_hz
        clients: list[socket.socket] = []
        self.tcp.settimeout(0.0)
        next_t = time.monotonic()
        while not self._stop.is_set():
            while True:
                try:
                    conn, _ = self.tcp.accept()
                except (BlockingIOError, OSError):
                    break
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                conn.settimeout(period)
                clients.append(conn)
            if clients:
                try:
                    data = encode_frame(self.perception_frame())
                except Exception as err:  # noqa: BLE001 -- keep serving
                    log.warning("perception frame failed: %s", err)
                    data = b""
                for conn in list(clients):
                    try:
                        if data:
                            conn.sendall(data)
                    except OSError:
                        clients.remove(conn)
                        conn.close()
            next_t = max(next_t + period, time.monotonic())
            self._stop.wait(max(0.0, next_t - time.monotonic()))
        for conn in clients:
            conn.close()


__all__ = ["MovingObstacles", "SimStats", "SimVehicle", "SimVehicleConfig", "parse_hostport"]
