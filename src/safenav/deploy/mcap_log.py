"""Flight logs in MCAP with ROS 2 message schemas (``safenav fly --record``, ``safenav render
--record``), for Foxglove and the ROS 2 tools (docs/deployment.md, "Flight logs (MCAP)").

One :class:`McapRecorder` writes both the logs of real or simulated PX4 flights and those of
simulator episodes. Messages are ROS 2 messages serialised as CDR by ``mcap-ros2-support`` (no ROS
installation needed), each channel with its complete ``ros2msg`` schema (the definitions below,
field for field those of ROS 2 Humble / Jazzy, so that ``ros2 bag play`` republishes them as the
real types). Topics, all in the world frame ``map`` (ENU: x east, y north, z up; REP 103) unless
said otherwise:

=========================  ===============================  ===================================
topic                      type                             what
=========================  ===============================  ===================================
``/tf``                    ``tf2_msgs/msg/TFMessage``       ``map`` -> ``base_link`` (the UAV)
``/safenav/pose``          ``nav_msgs/msg/Odometry``        position, heading; velocity in
                                                            ``base_link`` (REP 105)
``/safenav/setpoint``      ``geometry_msgs/msg/TwistStamped``  the velocity command sent, in
                                                            ``base_link`` (= the goal frame: the
                                                            policy's action x v_max; zero while
                                                            hovering)
``/safenav/range_image``   ``sensor_msgs/msg/Image``        the policy's range image, ``32FC1``
                                                            metres, ``base_link``
``/safenav/range_points``  ``sensor_msgs/msg/PointCloud2``  its returns as points (x, y, z,
                                                            range), for the 3D panel
``/safenav/obstacles``     ``visualization_msgs/msg/MarkerArray``  moving obstacles: cylinders
                                                            and floating cuboids
``/safenav/map``           ``visualization_msgs/msg/MarkerArray``  the static scene: pillars (when
                                                            known), arena border, start, goal
``/safenav/goal``          ``geometry_msgs/msg/PoseStamped``  the goal (heading: the goal frame)
=========================  ===============================  ===================================

Why the range image is both an ``Image`` and a ``PointCloud2``: the ``Image`` is the exact
observation (4 elevations x 36 azimuths, metres; row 0 is the highest elevation so that it is
upright, column ``j`` looks ``360 j / 36`` degrees counter-clockwise from the heading; "no
return" is the beam's range, 4 m): Foxglove's Image panel shows a ``32FC1`` image with a colour
map, at the resolution the policy sees. Shown in 3D it says little; the same beams' returns as
points, in ``map``, sit on the obstacles they hit in the 3D panel. A ``LaserScan`` holds one
elevation only.

``/safenav/map`` is republished every ``map_period_s`` (1 s) so that a viewer that seeks, or a
``ros2 bag play`` subscriber that joins late, gets the static scene within a second. Moving
obstacles keep their marker ids while they are tracked; a marker whose obstacle is gone is
deleted (``DELETE``), so every viewer (Foxglove, RViz) shows the current set.

Time stamps (header stamps = MCAP log times): a flight's are the wall-clock time of the flight
(``time.monotonic()`` of each control tick, moved onto UTC once at the start, so they increase
even if NTP adjusts the clock); a simulator episode's are its simulation time (step x dt from 0).

Writing happens in a background thread when ``threaded`` (a flight: the control loop only queues
NumPy arrays, it never waits for a disk); the file is written as it goes, so a crash leaves a
readable prefix (``mcap recover``).
"""

from __future__ import annotations

import logging
import math
import queue
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from safenav.errors import SafenavError, SafenavRuntimeError

log = logging.getLogger("safenav.deploy.mcap_log")

WORLD_FRAME = "map"
BODY_FRAME = "base_link"

TOPICS: dict[str, str] = {
    "/tf": "tf2_msgs/msg/TFMessage",
    "/safenav/pose": "nav_msgs/msg/Odometry",
    "/safenav/setpoint": "geometry_msgs/msg/TwistStamped",
    "/safenav/range_image": "sensor_msgs/msg/Image",
    "/safenav/range_points": "sensor_msgs/msg/PointCloud2",
    "/safenav/obstacles": "visualization_msgs/msg/MarkerArray",
    "/safenav/map": "visualization_msgs/msg/MarkerArray",
    "/safenav/goal": "geometry_msgs/msg/PoseStamped",
}
"""Topic -> ROS 2 message type of every channel a recording has."""

# The ROS 2 message definitions (ROS 2 Jazzy's common_interfaces, comments left out; the same
# wire layout as Humble's), one per type, without their dependencies: msgdef() concatenates them.
MSGDEFS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec",
    "builtin_interfaces/msg/Duration": "int32 sec\nuint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "std_msgs/msg/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\nPose pose",
    "geometry_msgs/msg/Twist": "Vector3 linear\nVector3 angular",
    "geometry_msgs/msg/TwistStamped": "std_msgs/Header header\nTwist twist",
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance",
    "geometry_msgs/msg/TwistWithCovariance": "Twist twist\nfloat64[36] covariance",
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation",
    "geometry_msgs/msg/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\nTransform transform"
    ),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist"
    ),
    "sensor_msgs/msg/Image": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data"
    ),
    "sensor_msgs/msg/PointField": (
        "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\n"
        "uint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\n"
        "string name\nuint32 offset\nuint8 datatype\nuint32 count"
    ),
    "sensor_msgs/msg/PointCloud2": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\n"
        "bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense"
    ),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data",
    "visualization_msgs/msg/UVCoordinate": "float32 u\nfloat32 v",
    "visualization_msgs/msg/MeshFile": "string filename\nuint8[] data",
    "visualization_msgs/msg/Marker": (
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\n"
        "int32 LINE_LIST=5\nint32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\n"
        "int32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\nint32 TRIANGLE_LIST=11\n"
        "int32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n"
        "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\n"
        "geometry_msgs/Pose pose\ngeometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\n"
        "builtin_interfaces/Duration lifetime\nbool frame_locked\ngeometry_msgs/Point[] points\n"
        "std_msgs/ColorRGBA[] colors\nstring texture_resource\n"
        "sensor_msgs/CompressedImage texture\nUVCoordinate[] uv_coordinates\nstring text\n"
        "string mesh_resource\nMeshFile mesh_file\nbool mesh_use_embedded_materials"
    ),
    "visualization_msgs/msg/MarkerArray": "Marker[] markers",
}

_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
               "int32", "uint32", "int64", "uint64", "string", "wstring"}  # fmt: skip
_SEPARATOR = "=" * 80


def _dependencies(name: str) -> list[str]:
    """The message types the fields of ``name`` (``pkg/msg/Type``) use, in field order."""
    package = name.split("/")[0]
    out = []
    for line in MSGDEFS[name].splitlines():
        words = line.split()
        if len(words) < 2 or "=" in words[1] or "=" in words[0]:
            continue  # a constant
        ftype = re.sub(r"(\[.*\]|<=\d+)$", "", words[0])
        if ftype in _PRIMITIVES:
            continue
        pkg, _, short = ftype.rpartition("/")
        out.append(f"{pkg or package}/msg/{short}")
    return out


def msgdef(name: str) -> str:
    """The complete ``ros2msg`` definition of ``name``: its own, then each type it uses
    (recursively, once) after a line of 80 ``=`` and ``MSG: pkg/msg/Type`` (rosbag2's format,
    docs/message_definition_encoding.md of rosbag2)."""
    seen: list[str] = []

    def visit(n: str) -> None:
        for dep in _dependencies(n):
            if dep not in seen:
                seen.append(dep)
                visit(dep)

    visit(name)
    parts = [MSGDEFS[name]] + [f"{_SEPARATOR}\nMSG: {dep}\n{MSGDEFS[dep]}" for dep in seen]
    return "\n".join(parts) + "\n"


# ------------------------------------------------------------------------------ checks


def require_mcap(flag: str = "--record") -> None:
    """``SafenavRuntimeError`` (exit 1) naming the fix if ``mcap`` / ``mcap-ros2-support`` are
    missing."""
    try:
        import mcap.reader  # noqa: F401
        import mcap_ros2.writer  # noqa: F401
    except ImportError as err:
        raise SafenavRuntimeError(f"{flag} needs the mcap and mcap-ros2-support packages ({err}): "
                                  "pip install 'safenav[mcap]'") from None  # fmt: skip


def check_record_path(path: Path, flag: str = "--record") -> None:
    """Before any work: ``path`` can be written, is named ``*.mcap``, and the packages are here."""
    from safenav.common.checks import check_output_file

    check_output_file(path, flag, "flight.mcap")
    if Path(path).suffix.lower() != ".mcap":
        raise SafenavError(f"{flag} {path}: an MCAP file is written; name it *.mcap, "
                           f"e.g. {flag} flight.mcap")  # fmt: skip
    require_mcap(flag)


# ------------------------------------------------------------------------------ the scene


@dataclass
class Scene:
    """What does not move during a recording (``/safenav/map`` and ``/safenav/goal``)."""

    goal: np.ndarray
    """Goal, world ENU (m)."""
    goal_tolerance: float = 0.5
    goal_yaw: float = 0.0
    """Yaw (ENU, rad) of the goal frame: the heading the policy flies with."""
    start: np.ndarray | None = None
    arena_half: float | None = None
    """Half side of the square arena whose border is a wall (the geofence); None: no border."""
    pillars: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    """``(P, 4)``: centre x, y, half side of the square footprint, height (m). Known in the
    simulator; empty on a real flight."""
    v_angles: tuple[float, ...] = (-10.0, 0.0, 10.0, 20.0)
    """Elevations (degrees) of the range image's rows, the env's order."""
    max_range: float = 4.0
    """Beam range (m): a beam with this range has no return."""

    @staticmethod
    def for_env(cfg, goal, start=None, goal_yaw: float | None = None, world=None,
                arena: bool = True) -> Scene:  # fmt: skip
        """The scene of an env config ``cfg``, with ``world``'s active pillars when given."""
        from safenav.deploy.frames import goal_frame_yaw

        goal = np.asarray(goal, dtype=float).reshape(3)
        start = None if start is None else np.asarray(start, dtype=float).reshape(3)
        if goal_yaw is None:
            goal_yaw = goal_frame_yaw(start, goal) if start is not None else 0.0
        pillars = np.zeros((0, 4))
        if world is not None:
            ns = cfg.active_static
            pillars = np.column_stack([np.asarray(world.pillar_xy[:ns], dtype=float),
                                       np.asarray(world.pillar_half[:ns], dtype=float),
                                       np.asarray(world.pillar_height[:ns], dtype=float)])  # fmt: skip
        return Scene(goal=goal, goal_tolerance=float(cfg.goal_tolerance), goal_yaw=float(goal_yaw),
                     start=start, arena_half=float(cfg.half) if arena else None, pillars=pillars,
                     v_angles=tuple(float(a) for a in cfg.lidar_v_angles),
                     max_range=float(cfg.lidar_range))  # fmt: skip


# ------------------------------------------------------------------------------ messages

# Colours (RGBA, 0-1) of the top-down renderer (safenav.envs.render).
PILLAR_RGBA = (95 / 255, 100 / 255, 110 / 255, 1.0)
CYLINDER_RGBA = (230 / 255, 140 / 255, 40 / 255, 0.9)
CUBOID_RGBA = (70 / 255, 130 / 255, 220 / 255, 0.9)
GOAL_RGBA = (30 / 255, 170 / 255, 60 / 255, 0.5)
START_RGBA = (40 / 255, 40 / 255, 200 / 255, 0.8)
WALL_RGBA = (40 / 255, 40 / 255, 45 / 255, 1.0)

CUBE, SPHERE, CYLINDER, LINE_STRIP = 1, 2, 3, 4
ADD, DELETE = 0, 2
FLOAT32 = 7


def _stamp(ns: int) -> dict[str, int]:
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def _header(ns: int, frame: str = WORLD_FRAME) -> dict[str, Any]:
    return {"stamp": _stamp(ns), "frame_id": frame}


def _xyz(v) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _yaw_quaternion(yaw: float) -> dict[str, float]:
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}


def _rgba(c) -> dict[str, float]:
    return {"r": c[0], "g": c[1], "b": c[2], "a": c[3]}


def _marker(ns: int, name: str, ident: int, kind: int, centre, scale, rgba, yaw: float = 0.0,
            action: int = ADD, **extra) -> dict[str, Any]:  # fmt: skip
    return {"header": _header(ns), "ns": name, "id": int(ident), "type": kind, "action": action,
            "pose": {"position": _xyz(centre), "orientation": _yaw_quaternion(yaw)},
            "scale": _xyz(scale), "color": _rgba(rgba), **extra}  # fmt: skip


def _finite(x) -> np.ndarray:
    return np.nan_to_num(np.asarray(x, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)


# ------------------------------------------------------------------------------ the recorder


class McapRecorder:
    """Writes a recording to ``path`` (``*.mcap``); see the module docstring.

    Call :meth:`record` once per control step with the vehicle's state (and, when there is one,
    the setpoint sent, the range image and the moving obstacles), then :meth:`close`. ``t`` is in
    seconds: ``time.monotonic()`` for a flight (``clock="monotonic"``: stamps are UTC), the
    simulation time for an episode (``clock="sim"``: stamps are ``t``).

    Args:
        path: the file (overwritten).
        scene: the static scene (goal, pillars, ...).
        clock: ``"monotonic"`` or ``"sim"`` (see above).
        threaded: write in a background thread (:meth:`record` only queues its arrays).
        map_period_s: republish ``/safenav/map`` and ``/safenav/goal`` this often (seconds of ``t``).
        metadata: stored as the file's ``safenav`` metadata record (preset, policy, ...; as
            strings; with mcap-ros2-support >= 0.6, older versions write no metadata).
    """

    def __init__(self, path: str | Path, scene: Scene, clock: str = "monotonic",
                 threaded: bool = True, map_period_s: float = 1.0,
                 metadata: dict[str, Any] | None = None) -> None:  # fmt: skip
        from mcap_ros2.writer import Writer

        if clock not in ("monotonic", "sim"):
            raise ValueError(f"clock {clock!r}: 'monotonic' or 'sim'")
        self.path, self.scene, self.map_period_s = Path(path), scene, float(map_period_s)
        self._offset_ns = (time.time_ns() - time.monotonic_ns()) if clock == "monotonic" else 0
        try:
            self._file = open(self.path, "wb")  # noqa: SIM115 -- closed in close()
        except OSError as err:
            raise SafenavRuntimeError(
                f"--record {path}: cannot write it ({err.strerror or err})"
            ) from None
        try:
            self._writer = Writer(self._file)
            self._schemas = {t: self._writer.register_msgdef(t, msgdef(t))
                             for t in sorted(set(TOPICS.values()))}  # fmt: skip
            add_metadata = getattr(self._writer, "add_metadata", None)  # mcap-ros2-support >= 0.6
            if add_metadata is not None:
                add_metadata("safenav", {str(k): str(v) for k, v in (metadata or {}).items()})
        except BaseException:
            self._file.close()
            raise
        self.counts: dict[str, int] = dict.fromkeys(TOPICS, 0)
        self.error: str | None = None
        self._last_ns = -1
        self._last_map_t = -math.inf
        self._scene_changed = False
        self._movers_shown = 0
        self._closed = False
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        if threaded:
            self._queue = queue.Queue(maxsize=10_000)
            self._thread = threading.Thread(target=self._drain, name="mcap-recorder", daemon=True)
            self._thread.start()

    # ---------------------------------------------------------------- the public side
    def record(self, t: float, pos, vel, yaw: float, setpoint=None, ranges=None,
               movers=None) -> None:  # fmt: skip
        """One step at time ``t`` (s).

        Args:
            pos, vel: the vehicle's position and velocity, world ENU.
            yaw: its heading (ENU, rad).
            setpoint: the velocity command sent at ``t`` (world ENU; written in ``base_link``),
                or None (no command).
            ranges: the range image ``(V, H)`` in metres (the env's layout), or None.
            movers: ``(M, 6)`` moving obstacles: centre x y z, width, height, cuboid (0/1); or
                None (no tracker output this step).
        """
        if self._closed or self.error is not None:
            return
        item = (float(t), np.array(pos, dtype=float), np.array(vel, dtype=float), float(yaw),
                None if setpoint is None else np.array(setpoint, dtype=float),
                None if ranges is None else np.array(ranges, dtype=np.float32),
                None if movers is None else np.array(movers, dtype=float).reshape(-1, 6))  # fmt: skip
        if self._queue is None:
            self._guarded(self._write_step, *item)
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:  # the disk cannot keep up: drop, never block the control loop
            self.error = "the writer fell behind (queue full); recording stopped"
            log.error("--record %s: %s", self.path, self.error)

    def update_scene(self, **changes: Any) -> None:
        """Change fields of the scene (e.g. ``start`` and ``goal_yaw`` once the vehicle has taken
        off); ``/safenav/map`` and ``/safenav/goal`` are republished at the next step."""
        import dataclasses

        self.scene = dataclasses.replace(self.scene, **changes)  # one reference swap: thread-safe
        self._scene_changed = True

    def close(self) -> dict[str, int]:
        """Finish the file (summary and index); returns the messages written per topic. Never
        raises: a failure is in :attr:`error` (and logged)."""
        if self._closed:
            return self.counts
        self._closed = True
        if self._thread is not None and self._queue is not None:
            self._queue.put(None)
            self._thread.join()
        try:
            self._writer.finish()
        except Exception as err:  # noqa: BLE001 -- disk full, ...: reported, not raised
            self.error = self.error or f"finishing the file failed: {err}"
        finally:
            try:
                self._file.close()
            except OSError as err:
                self.error = self.error or f"closing the file failed: {err}"
        if self.error:
            log.error("--record %s: %s", self.path, self.error)
        return self.counts

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---------------------------------------------------------------- the writer side
    def _drain(self) -> None:
        assert self._queue is not None
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self.error is None:
                self._guarded(self._write_step, *item)

    def _guarded(self, fn, *args) -> None:
        try:
            fn(*args)
        except Exception as err:  # noqa: BLE001 -- a log must never stop a flight
            self.error = f"writing failed: {type(err).__name__}: {err}"
            log.error("--record %s: %s", self.path, self.error)

    def _write(self, topic: str, ns: int, message: dict[str, Any]) -> None:
        self._writer.write_message(topic, self._schemas[TOPICS[topic]], message, log_time=ns,
                                   publish_time=ns, sequence=self.counts[topic])  # fmt: skip
        self.counts[topic] += 1

    def _write_step(self, t, pos, vel, yaw, setpoint, ranges, movers) -> None:
        ns = int(round(t * 1e9)) + self._offset_ns
        if ns <= self._last_ns:  # a repeated or earlier stamp: keep every topic increasing
            ns = self._last_ns + 1
        self._last_ns = ns
        if t - self._last_map_t >= self.map_period_s or self._scene_changed:
            self._last_map_t, self._scene_changed = t, False
            self._write_scene(ns)
        pos, vel = _finite(pos), _finite(vel)
        yaw = yaw if math.isfinite(yaw) else 0.0
        q = _yaw_quaternion(yaw)
        self._write("/tf", ns, {"transforms": [{
            "header": _header(ns), "child_frame_id": BODY_FRAME,
            "transform": {"translation": _xyz(pos), "rotation": q},
        }]})  # fmt: skip
        c, s = math.cos(yaw), math.sin(yaw)

        def body(v) -> tuple[float, float, float]:  # world ENU -> base_link (yaw only)
            return (c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2])

        self._write("/safenav/pose", ns, {
            "header": _header(ns), "child_frame_id": BODY_FRAME,
            "pose": {"pose": {"position": _xyz(pos), "orientation": q}, "covariance": [0.0] * 36},
            "twist": {"twist": {"linear": _xyz(body(vel)), "angular": _xyz((0, 0, 0))},
                      "covariance": [0.0] * 36},
        })  # fmt: skip
        if setpoint is not None:
            self._write("/safenav/setpoint", ns, {
                "header": _header(ns, BODY_FRAME),
                "twist": {"linear": _xyz(body(_finite(setpoint))), "angular": _xyz((0, 0, 0))},
            })  # fmt: skip
        if ranges is not None:
            self._write_ranges(ns, pos, yaw, ranges)
        if movers is not None:
            self._write_movers(ns, movers)

    def _write_scene(self, ns: int) -> None:
        sc = self.scene
        markers = []
        for i, (x, y, half, height) in enumerate(sc.pillars):
            markers.append(_marker(ns, "pillars", i, CUBE, (x, y, height / 2),
                                   (2 * half, 2 * half, height), PILLAR_RGBA))  # fmt: skip
        r = sc.goal_tolerance
        markers.append(_marker(ns, "goal", 0, SPHERE, sc.goal, (2 * r, 2 * r, 2 * r), GOAL_RGBA))
        if sc.start is not None:
            markers.append(_marker(ns, "start", 0, CUBE, (sc.start[0], sc.start[1], 0.025),
                                   (0.3, 0.3, 0.05), START_RGBA))  # fmt: skip
        if sc.arena_half is not None:
            h = sc.arena_half
            corners = [(-h, -h, 0.0), (h, -h, 0.0), (h, h, 0.0), (-h, h, 0.0), (-h, -h, 0.0)]
            markers.append(_marker(ns, "border", 0, LINE_STRIP, (0, 0, 0), (0.15, 0, 0), WALL_RGBA,
                                   points=[_xyz(p) for p in corners]))  # fmt: skip
        self._write("/safenav/map", ns, {"markers": markers})
        self._write("/safenav/goal", ns, {
            "header": _header(ns),
            "pose": {"position": _xyz(sc.goal), "orientation": _yaw_quaternion(sc.goal_yaw)},
        })  # fmt: skip

    def _write_ranges(self, ns: int, pos, yaw: float, ranges: np.ndarray) -> None:
        sc = self.scene
        ranges = np.nan_to_num(ranges, nan=sc.max_range, posinf=sc.max_range, neginf=0.0)
        v, h = ranges.shape
        upright = np.ascontiguousarray(ranges[::-1], dtype="<f4")  # row 0: highest elevation
        self._write("/safenav/range_image", ns, {
            "header": _header(ns, BODY_FRAME), "height": v, "width": h, "encoding": "32FC1",
            "is_bigendian": 0, "step": 4 * h, "data": upright.tobytes(),
        })  # fmt: skip
        elev = np.radians(np.asarray(sc.v_angles[:v], dtype=float))[:, None]
        az = yaw + 2 * np.pi * np.arange(h)[None, :] / h
        hit = ranges < sc.max_range - 1e-4
        d = ranges.astype(float)
        pts = np.stack([pos[0] + d * np.cos(elev) * np.cos(az), pos[1] + d * np.cos(elev) * np.sin(az),
                        pos[2] + d * np.sin(elev), d], -1)[hit]  # fmt: skip
        data = np.ascontiguousarray(pts, dtype="<f4")
        self._write("/safenav/range_points", ns, {
            "header": _header(ns), "height": 1, "width": len(data),
            "fields": [{"name": n, "offset": 4 * i, "datatype": FLOAT32, "count": 1}
                       for i, n in enumerate(("x", "y", "z", "range"))],
            "is_bigendian": False, "point_step": 16, "row_step": 16 * len(data),
            "data": data.tobytes(), "is_dense": True,
        })  # fmt: skip

    def _write_movers(self, ns: int, movers: np.ndarray) -> None:
        markers = []
        for i, (x, y, z, width, height, cuboid) in enumerate(movers):
            if not all(map(math.isfinite, (x, y, z, width, height))):
                continue
            markers.append(_marker(ns, "movers", i, CUBE if cuboid else CYLINDER, (x, y, z),
                                   (width, width, height), CUBOID_RGBA if cuboid else CYLINDER_RGBA))  # fmt: skip
        for i in range(len(movers), self._movers_shown):  # gone since the last step
            markers.append(_marker(ns, "movers", i, CUBE, (0, 0, 0), (1, 1, 1), (0, 0, 0, 0),
                                   action=DELETE))  # fmt: skip
        self._movers_shown = len(movers)
        self._write("/safenav/obstacles", ns, {"markers": markers})


def read_summary(path: str | Path) -> dict[str, Any]:
    """Topics, their schemas and message counts, and the time span of an MCAP file (from its
    summary section)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    if summary is None or summary.statistics is None:
        raise SafenavError(f"{path}: no MCAP summary (an unfinished recording? `mcap recover`)")
    st = summary.statistics
    topics = {ch.topic: {"schema": summary.schemas[ch.schema_id].name,
                         "messages": st.channel_message_counts.get(cid, 0)}
              for cid, ch in summary.channels.items()}  # fmt: skip
    return {
        "topics": topics,
        "messages": st.message_count,
        "start_s": st.message_start_time / 1e9,
        "end_s": st.message_end_time / 1e9,
    }


__all__ = [
    "MSGDEFS",
    "TOPICS",
    "McapRecorder",
    "Scene",
    "check_record_path",
    "msgdef",
    "read_summary",
    "require_mcap",
]
