"""Flight logs in MCAP with ROS 2 messages (``safenav fly --record``, ``safenav render --record``),
read back with the ``mcap`` library and ``mcap-ros2-support``'s CDR decoder, as Foxglove and
``ros2 bag`` read them."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("mcap_ros2")

from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402

from safenav.cli import main  # noqa: E402
from safenav.deploy.mcap_log import TOPICS, McapRecorder, Scene, msgdef  # noqa: E402

CLI = [sys.executable, "-c", "from safenav.cli import main; main()"]
FLIGHT_TOPICS = set(TOPICS)  # every topic, in a flight and in an episode


def read_back(path: Path) -> tuple[dict, dict[str, list]]:
    """``(summary, {topic: [(log_time, decoded message), ...]})`` of an MCAP file."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None  # a finished file
        by_topic: dict[str, list] = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            assert schema.name == TOPICS[channel.topic], channel.topic
            by_topic.setdefault(channel.topic, []).append((message.log_time, decoded))
    return summary, by_topic


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def check_recording(path: Path, half: float, z_max: float = 4.0, max_range: float = 4.0) -> dict:
    """The checks every recording passes; returns ``{topic: messages}``."""
    summary, msgs = read_back(path)
    assert set(msgs) == FLIGHT_TOPICS, set(msgs) ^ FLIGHT_TOPICS
    schemas = {summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
    assert schemas == set(TOPICS.values())
    for topic, items in msgs.items():
        times = [t for t, _ in items]
        assert len(times) > 0 and all(b > a for a, b in zip(times, times[1:], strict=False)), topic
        if topic == "/tf":
            stamps = [stamp_ns(m.transforms[0]) for _, m in items]
        elif topic in ("/safenav/obstacles", "/safenav/map"):
            stamps = [stamp_ns(m.markers[0]) if m.markers else t for t, m in items]
        else:
            stamps = [stamp_ns(m) for _, m in items]
        assert stamps == times, f"{topic}: header stamps are the log times"
    # the vehicle stays in the arena, between the ground and the ceiling
    pos = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z]
                    for _, m in msgs["/safenav/pose"]])  # fmt: skip
    assert np.isfinite(pos).all()
    assert (np.abs(pos[:, :2]) <= half + 0.5).all() and (pos[:, 2] >= -0.1).all()
    assert (pos[:, 2] <= z_max + 0.5).all() and pos[:, 2].max() > 0.3  # it flew
    odo = msgs["/safenav/pose"][0][1]
    assert odo.header.frame_id == "map" and odo.child_frame_id == "base_link"
    q = odo.pose.pose.orientation
    assert abs(q.x**2 + q.y**2 + q.z**2 + q.w**2 - 1) < 1e-9 and len(odo.pose.covariance) == 36
    tf = msgs["/tf"][0][1].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "base_link")
    # setpoints: in base_link = the goal frame, within v_max (2 m/s) per axis as the env clamps
    v = np.array([[m.twist.linear.x, m.twist.linear.y, m.twist.linear.z]
                  for _, m in msgs["/safenav/setpoint"]])  # fmt: skip
    assert msgs["/safenav/setpoint"][0][1].header.frame_id == "base_link"
    assert np.isfinite(v).all() and (np.abs(v) <= 2.0 + 1e-6).all()
    assert np.linalg.norm(v, axis=1).max() > 0.1  # it was commanded to move
    # the range image: 32FC1, 4 x 36, metres in [0, max_range]
    for _, img in msgs["/safenav/range_image"]:
        assert (img.encoding, img.height, img.width, img.step) == ("32FC1", 4, 36, 144)
        assert img.header.frame_id == "base_link"
        r = np.frombuffer(bytes(img.data), "<f4")
        assert r.size == 4 * 36 and (r >= 0).all() and (r <= max_range + 1e-5).all()
    clouds = [m for _, m in msgs["/safenav/range_points"]]
    assert [f.name for f in clouds[0].fields] == ["x", "y", "z", "range"]
    assert any(c.width > 0 for c in clouds)  # something was in range: the ground, a pillar
    for c in clouds:
        pts = np.frombuffer(bytes(c.data), "<f4").reshape(-1, 4)
        assert pts.shape[0] == c.width and (pts[:, 3] < max_range).all()
    # the static scene: the goal in the map, the arena's border
    scene = msgs["/safenav/map"][-1][1].markers
    kinds = {m.ns for m in scene}
    assert {"goal", "border"} <= kinds
    goal = msgs["/safenav/goal"][-1][1].pose.position
    assert abs(goal.x) <= half and abs(goal.y) <= half and 0 < goal.z <= z_max
    return msgs


# ------------------------------------------------------------------------------ unit


def test_every_schema_is_a_complete_ros2msg_definition():
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

    for name in set(TOPICS.values()):
        text = msgdef(name)
        decoders, encoders = generate_dynamic(name, text), serialize_dynamic(name, text)
        assert name in decoders and name in encoders
        for block in text.split("=" * 80 + "\n")[1:]:
            assert block.startswith("MSG: ") and "/msg/" in block.splitlines()[0]
    marker = msgdef("visualization_msgs/msg/MarkerArray")
    for dep in ("std_msgs/msg/Header", "builtin_interfaces/msg/Time", "geometry_msgs/msg/Pose",
                "sensor_msgs/msg/CompressedImage", "visualization_msgs/msg/MeshFile"):  # fmt: skip
        assert f"MSG: {dep}\n" in marker
        assert marker.count(f"MSG: {dep}\n") == 1


@pytest.mark.parametrize("threaded", [False, True])
def test_recorder_round_trip(tmp_path, threaded):
    scene = Scene(goal=np.array([3.0, 4.0, 1.5]), start=np.array([0.0, 0.0, 1.0]), arena_half=10.0,
                  pillars=np.array([[2.0, 2.0, 0.4, 3.0], [-1.0, 5.0, 0.25, 1.0]]))  # fmt: skip
    path = tmp_path / "r.mcap"
    rec = McapRecorder(path, scene, clock="sim", threaded=threaded, metadata={"test": 1})
    ranges = np.full((4, 36), 4.0, dtype=np.float32)
    ranges[1, 0] = 1.5  # one return straight ahead at 0 degrees
    for k in range(30):
        movers = np.array([[1, 1, 2.5, 0.6, 5.0, 0], [2, 2, 1.0, 0.8, 1.0, 1]])[: 2 - (k >= 20)]
        rec.record(k * 0.1, (0.1 * k, 0, 1.0), (1.0, 0, 0), 0.0, setpoint=(1.0, 0, 0),
                   ranges=ranges, movers=movers)  # fmt: skip
    rec.record(3.0, (3.0, 0, 1.0), (float("nan"), 0, 0), float("nan"))  # bad data: no crash
    counts = rec.close()
    assert rec.error is None and counts["/safenav/pose"] == 31 and counts["/safenav/setpoint"] == 30
    assert counts["/safenav/map"] == 4  # t = 0, 1, 2, 3 s
    msgs = check_recording(path, half=10.0)
    pts = np.frombuffer(bytes(msgs["/safenav/range_points"][0][1].data), "<f4").reshape(-1, 4)
    np.testing.assert_allclose(pts, [[1.5, 0.0, 1.0, 1.5]], atol=1e-6)  # heading 0, elevation 0
    img = np.frombuffer(bytes(msgs["/safenav/range_image"][0][1].data), "<f4").reshape(4, 36)
    assert img[2, 0] == 1.5  # upright: row 0 = 20 deg, row 2 = 0 deg
    scene_ns = [m.ns for m in msgs["/safenav/map"][0][1].markers]
    assert scene_ns.count("pillars") == 2 and {"goal", "start", "border"} <= set(scene_ns)
    pillar = msgs["/safenav/map"][0][1].markers[0]
    assert (pillar.type, pillar.pose.position.z, pillar.scale.x, pillar.scale.z) == (
        1,
        1.5,
        0.8,
        3.0,
    )
    first, gone = (
        msgs["/safenav/obstacles"][0][1].markers,
        msgs["/safenav/obstacles"][20][1].markers,
    )
    assert [(m.type, m.action) for m in first] == [(3, 0), (1, 0)]  # a cylinder and a cuboid
    assert [(m.id, m.action) for m in gone] == [(0, 0), (1, 2)]  # the second one left: DELETE
    with open(path, "rb") as f:
        meta = list(make_reader(f).iter_metadata())
    if hasattr(rec._writer, "add_metadata"):  # mcap-ros2-support >= 0.6
        assert meta[0].name == "safenav" and meta[0].metadata == {"test": "1"}


def test_missing_packages_are_one_line_with_the_fix(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "mcap_ros2.writer", None)  # import fails
    with pytest.raises(SystemExit) as exc:
        main(["render", "--policy", "scripted", "--out", str(tmp_path / "e.gif"), "--record",
              str(tmp_path / "e.mcap")])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 1 and len(err) == 1 and "pip install 'safenav[mcap]'" in err[0]
    assert err[0].startswith("safenav: error: --record") and not list(tmp_path.iterdir())


@pytest.mark.parametrize("name", ["e.gif", "e.bag", "adir"])
def test_record_paths_are_checked_before_the_flight(tmp_path, capsys, name):
    (tmp_path / "adir").mkdir()
    for argv in (["render", "--policy", "scripted", "--out", str(tmp_path / "x.gif")],
                 ["fly", "--demo", "--scripted", "--gif", str(tmp_path / "f.gif"),
                  "--connect", "udpin://127.0.0.1:0"]):  # fmt: skip
        with pytest.raises(SystemExit) as exc:
            main([*argv, "--record", str(tmp_path / name)])
        err = capsys.readouterr().err.strip().splitlines()
        assert (
            exc.value.code == 2 and len(err) == 1 and err[0].startswith("safenav: error: --record")
        )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir"]  # nothing written


class FakeVehicle:
    """A vehicle that hovers where it is (local NED), accepts every command."""

    url = "fake://"

    def __init__(self) -> None:
        self.mode, self.airborne, self.sent = "HOLD", False, []

    def latest(self):
        from safenav.deploy.fly import Telemetry

        return Telemetry(np.array([0.0, 0.0, -1.5]), np.zeros(3), time.monotonic())

    def connect(self, timeout_s): ...
    def wait_ready(self, timeout_s): ...
    def arm(self): ...
    def flight_mode(self):
        return self.mode

    def in_air(self):
        return self.airborne

    def takeoff(self, altitude_m):
        self.airborne = True

    def start_offboard(self, yaw_deg):
        self.mode = "OFFBOARD"

    def send_velocity_ned(self, v_ned, yaw_deg):
        self.sent.append(np.asarray(v_ned, dtype=float))

    def hold(self):
        self.mode = "HOLD"

    def land(self):
        self.airborne = False

    def close(self): ...


def test_flight_controller_records_what_it_sends(tmp_path):
    """The control loop hands every tick to the recorder: the setpoint it sent (in base_link, the
    goal frame: the policy's action x v_max), the range image the policy saw, the tracked
    obstacles; hover ticks (no map yet) as zero setpoints without a range image."""
    from safenav.deploy.fly import FlightAborted, FlightController, FlyConfig
    from safenav.deploy.perception_link import PerceptionFrame, TrackedObstacle
    from safenav.deploy.runtime import OnboardRuntime, RuntimeConfig
    from safenav.envs.config import make_config

    cfg = make_config("easy")
    runtime = OnboardRuntime(lambda s, l, d: np.array([[0.5, -0.25, 0.0]], np.float32), cfg,  # noqa: E741
                             RuntimeConfig(require_tracker=False))  # fmt: skip
    goal = (8.0, 6.0, 1.5)  # from (0, 0): goal yaw atan2(6, 8), not 0
    rec = McapRecorder(tmp_path / "f.mcap", Scene.for_env(cfg, goal))
    ctl = FlightController(runtime, FakeVehicle(), FlyConfig(goal=goal, takeoff_altitude=0.0, max_flight_s=1.0),
                           recorder=rec)  # fmt: skip
    stop = threading.Event()
    tracked = [TrackedObstacle(np.array([2.0, 1.0, 0.5]), np.zeros(3), 0.8, 1.0)]

    def perception():  # the map (and a tracked cuboid) arrive after 0.3 s
        time.sleep(0.3)
        while not stop.is_set():
            ctl._on_frame(PerceptionFrame(time.monotonic(), points=np.zeros((0, 3), np.float32),
                                          obstacles=tracked))  # fmt: skip
            time.sleep(0.03)

    threading.Thread(target=perception, daemon=True).start()
    try:
        with pytest.raises(FlightAborted, match="not reached"):
            ctl.fly()
    finally:
        stop.set()
        rec.close()
    assert rec.error is None
    _, msgs = read_back(tmp_path / "f.mcap")
    v = np.array(
        [
            [m.twist.linear.x, m.twist.linear.y, m.twist.linear.z]
            for _, m in msgs["/safenav/setpoint"]
        ]
    )
    moving = v[np.abs(v).sum(1) > 0]
    assert len(moving) >= 5 and (np.abs(v).sum(1) == 0).sum() >= 2  # flew, and hovered first
    np.testing.assert_allclose(moving, np.tile([1.0, -0.5, 0.0], (len(moving), 1)), atol=1e-9)
    # an observation on every moving tick, and on a late one (zero setpoint) under a loaded CPU
    assert len(moving) <= len(msgs["/safenav/range_image"]) <= len(moving) + ctl.log.late_ticks
    cuboids = [mk for _, m in msgs["/safenav/obstacles"] for mk in m.markers]
    assert cuboids and all((mk.type, mk.scale.x, mk.scale.z) == (1, 0.8, 1.0) for mk in cuboids)
    q = msgs["/safenav/pose"][-1][1].pose.pose.orientation
    assert abs(2 * np.arctan2(q.z, q.w) - np.arctan2(6.0, 8.0)) < 1e-9  # heading: the goal frame
    assert msgs["/safenav/map"][-1][1].markers[0].ns == "goal"  # no ground truth: no pillars
    goal_yaw = msgs["/safenav/goal"][-1][1].pose.orientation
    assert abs(2 * np.arctan2(goal_yaw.z, goal_yaw.w) - np.arctan2(6.0, 8.0)) < 1e-9


# ------------------------------------------------------------------------------ end to end


def test_render_record(tmp_path, capsys):
    """``safenav render --record``: the episode in simulation time (t = step x 0.1 s from 0)."""
    out, rec = tmp_path / "e.gif", tmp_path / "e.mcap"
    main(
        [
            "render",
            "--policy",
            "scripted",
            "--preset",
            "easy",
            "--out",
            str(out),
            "--record",
            str(rec),
        ]
    )
    assert f"and {rec}" in capsys.readouterr().out and out.exists()
    msgs = check_recording(rec, half=10.0)
    times = [t for t, _ in msgs["/safenav/pose"]]
    assert times[0] == 0 and all(t % 100_000_000 == 0 for t in times)  # 10 Hz sim time
    assert len(msgs["/safenav/setpoint"]) == len(times) - 1  # no command after the last step
    pillars = [m for m in msgs["/safenav/map"][0][1].markers if m.ns == "pillars"]
    assert len(pillars) == 12  # the easy world's pillars
    movers = msgs["/safenav/obstacles"][0][1].markers
    assert len(movers) == 6 and {m.type for m in movers} <= {1, 3}  # easy: 6 moving obstacles


@pytest.mark.long
@pytest.mark.timeout(240)
def test_fly_demo_record(tmp_path):
    """``safenav fly --demo --record F.mcap`` (scripted actor, easy world, a short flight: the
    OFFBOARD phase is cut after 4 s, exit 3; the log of an aborted flight is complete too)."""
    pytest.importorskip("mavsdk")
    pytest.importorskip("onnxruntime")
    rec, js = tmp_path / "F.mcap", tmp_path / "f.json"
    proc = subprocess.run([*CLI, "fly", "--demo", "--scripted", "--preset", "easy", "--max-flight-time", "4",
                           "--gif", str(tmp_path / "f.gif"), "--json", str(js), "--record", str(rec)],
                          capture_output=True, text=True, timeout=200, cwd=tmp_path)  # fmt: skip
    assert proc.returncode in (0, 3, 4), proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and "--record" not in proc.stderr
    msgs = check_recording(rec, half=10.0)
    times = np.array([t for t, _ in msgs["/safenav/pose"]]) / 1e9
    assert times[0] > 1.7e9  # UTC, the flight's wall-clock time
    sp = np.array([t for t, _ in msgs["/safenav/setpoint"]]) / 1e9
    assert 3.5 <= sp[-1] - sp[0] <= 6.0 and len(sp) >= 40  # ~4 s of OFFBOARD at 20 Hz
    assert times[0] < sp[0]  # takeoff is in the log too
    movers = [m for _, m in msgs["/safenav/obstacles"]]
    assert all(mk.ns == "movers" for m in movers for mk in m.markers)
    scene = msgs["/safenav/map"][-1][1].markers
    assert sum(m.ns == "pillars" for m in scene) == 12  # the simulator's world
    summary = json.loads(js.read_text())
    assert summary["outcome"] in ("aborted", "reached_goal", "collided", "not_reached")
    # the flight's GIF is written whatever the outcome (an aborted one is one to watch too)
    assert (tmp_path / "f.gif").stat().st_size > 10_000 and summary["gif"] == str(
        tmp_path / "f.gif"
    )
    if summary["outcome"] == "aborted":
        assert f"flight GIF {tmp_path / 'f.gif'}" in proc.stderr.strip().splitlines()[-1]
