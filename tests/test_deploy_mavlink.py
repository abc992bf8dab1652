"""The simulated PX4 vehicle, spoken to in raw MAVLink (pymavlink) on loopback UDP."""

from __future__ import annotations

import math
import socket
import struct
import time

import numpy as np
import pytest
import torch
from pymavlink.dialects.v20 import common as mavlink

from safenav.deploy import px4
from safenav.deploy.demo import free_port
from safenav.deploy.sim_vehicle import MovingObstacles, SimVehicle, SimVehicleConfig
from safenav.envs import SafeNavVectorEnv, make_config
from safenav.envs.world import generate_world

M = mavlink


pytestmark = pytest.mark.usefixtures("one_thread")


class Gcs:
    """A minimal ground station: listens where the vehicle sends, replies to its address."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.mav = M.MAVLink(None, srcSystem=255, srcComponent=190)
        self.parser = M.MAVLink(None)
        self.vehicle: tuple[str, int] | None = None

    def send(self, msg) -> None:
        self.raw(msg.pack(self.mav))

    def raw(self, data: bytes) -> None:
        assert self.vehicle is not None
        self.sock.sendto(data, self.vehicle)

    def recv(self, kind: str, timeout: float = 3.0, cond=lambda m: True):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            try:
                data, addr = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            self.vehicle = addr
            for msg in self.parser.parse_buffer(data) or []:
                if msg.get_type() == kind and cond(msg):
                    return msg
        raise AssertionError(f"no {kind} within {timeout} s")

    def command(self, cmd: int, *params: float, timeout: float = 3.0) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        self.send(M.MAVLink_command_long_message(1, 1, cmd, 0, *p))
        return self.recv("COMMAND_ACK", timeout, lambda m: m.command == cmd).result

    def velocity(self, vn: float, ve: float, vd: float) -> None:
        mask = (
            0b0000_1101_1100_0111  # ignore position, acceleration, yaw rate; use velocity and yaw
        )
        self.send(M.MAVLink_set_position_target_local_ned_message(0, 1, 1, M.MAV_FRAME_LOCAL_NED, mask,
                                                                  0, 0, 0, vn, ve, vd, 0, 0, 0, 0.0, 0))  # fmt: skip

    def mode(self) -> tuple[int, int]:
        hb = self.recv("HEARTBEAT", 3.0)
        return px4.decode_custom_mode(hb.custom_mode)


@pytest.fixture
def link():
    gcs = Gcs()
    params = {"COM_OF_LOSS_T": 0.3, "MIS_TAKEOFF_ALT": 1.0, "MPC_TKO_SPEED": 3.0}
    sim = SimVehicle(
        SimVehicleConfig(connect=f"127.0.0.1:{gcs.port}", perception_port=-1, params=params)
    ).start()
    gcs.recv("HEARTBEAT")
    yield gcs, sim
    sim.stop()
    gcs.sock.close()


def set_mode(gcs: Gcs, main: int, sub: int = 0) -> int:
    return gcs.command(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub)


def take_off(gcs: Gcs, sim: SimVehicle) -> None:
    assert gcs.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    assert gcs.command(M.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7) == M.MAV_RESULT_ACCEPTED
    gcs.recv("EXTENDED_SYS_STATE", 5.0, lambda m: m.landed_state == M.MAV_LANDED_STATE_IN_AIR)


def test_looks_like_px4_to_a_ground_station(link) -> None:
    gcs, sim = link
    hb = gcs.recv("HEARTBEAT")
    assert hb.autopilot == M.MAV_AUTOPILOT_PX4 and hb.type == M.MAV_TYPE_QUADROTOR
    assert (
        hb.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        and not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    )
    assert px4.decode_custom_mode(hb.custom_mode) == (px4.MainMode.AUTO, px4.AutoSubMode.LOITER)
    st = gcs.recv("SYS_STATUS")
    for bit in (
        M.MAV_SYS_STATUS_PREARM_CHECK,
        M.MAV_SYS_STATUS_SENSOR_GPS,
        M.MAV_SYS_STATUS_SENSOR_3D_GYRO,
    ):
        assert st.onboard_control_sensors_present & bit and st.onboard_control_sensors_health & bit
    assert gcs.recv("GPS_RAW_INT").fix_type >= 3
    assert gcs.recv("EXTENDED_SYS_STATE").landed_state == M.MAV_LANDED_STATE_ON_GROUND
    lp = gcs.recv("LOCAL_POSITION_NED")  # NED: north = world y, east = world x
    assert (lp.x, lp.y, lp.z) == pytest.approx((sim.home[1], sim.home[0], 0.0), abs=1e-3)
    assert (
        gcs.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION)
        == M.MAV_RESULT_ACCEPTED
    )
    gcs.recv("HOME_POSITION")
    assert (
        gcs.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        == M.MAV_RESULT_ACCEPTED
    )
    assert gcs.recv("AUTOPILOT_VERSION").capabilities & M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    gcs.send(M.MAVLink_param_set_message(1, 1, b"MIS_TAKEOFF_ALT", 2.0, M.MAV_PARAM_TYPE_REAL32))
    pv = gcs.recv("PARAM_VALUE", 3.0, lambda m: m.param_id == "MIS_TAKEOFF_ALT")
    assert pv.param_value == pytest.approx(2.0) and sim.params["MIS_TAKEOFF_ALT"] == 2.0


def test_offboard_rules_and_velocity_setpoints(link) -> None:
    gcs, sim = link
    assert gcs.command(M.MAV_CMD_NAV_TAKEOFF) == M.MAV_RESULT_DENIED  # not armed
    take_off(gcs, sim)
    # OFFBOARD needs a setpoint stream first (PX4's rule).
    assert set_mode(gcs, px4.MainMode.OFFBOARD) == M.MAV_RESULT_DENIED
    for _ in range(5):
        gcs.velocity(1.0, 0.0, 0.0)
        time.sleep(0.02)
    assert set_mode(gcs, px4.MainMode.OFFBOARD) == M.MAV_RESULT_ACCEPTED
    y0 = sim.pos[1]
    for _ in range(50):  # 1 s north at 1 m/s, streamed at 50 Hz
        gcs.velocity(1.0, 0.0, 0.0)
        time.sleep(0.02)
    assert gcs.mode() == (px4.MainMode.OFFBOARD, 0)
    assert 0.4 < sim.pos[1] - y0 < 1.2  # north = +y in the world (ENU); first-order lag
    assert abs(sim.pos[0] - sim.home[0]) < 0.05
    # Setpoints stop: after COM_OF_LOSS_T PX4 fails over (COM_OBL_RC_ACT 5 = Hold).
    t0 = time.monotonic()
    while gcs.mode() != (px4.MainMode.AUTO, px4.AutoSubMode.LOITER):
        assert time.monotonic() - t0 < 3.0
    assert any("setpoints lost" in e for e in sim.events)
    # Land: descends, touches down, disarms (COM_DISARM_LAND).
    assert gcs.command(M.MAV_CMD_NAV_LAND) == M.MAV_RESULT_ACCEPTED
    gcs.recv("EXTENDED_SYS_STATE", 6.0, lambda m: m.landed_state == M.MAV_LANDED_STATE_ON_GROUND)


def test_offboard_loss_can_land(link) -> None:
    gcs, sim = link
    sim.params["COM_OBL_RC_ACT"] = float(px4.OBL_ACT_LAND)
    take_off(gcs, sim)
    gcs.velocity(0.0, 0.0, 0.0)
    assert set_mode(gcs, px4.MainMode.OFFBOARD) == M.MAV_RESULT_ACCEPTED
    gcs.recv(
        "HEARTBEAT",
        3.0,
        lambda m: (
            px4.decode_custom_mode(m.custom_mode) == (px4.MainMode.AUTO, px4.AutoSubMode.LAND)
        ),
    )


def test_malformed_and_unexpected_messages_are_ignored(link) -> None:
    gcs, sim = link
    gcs.recv("HEARTBEAT")
    good = M.MAVLink_heartbeat_message(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3).pack(
        gcs.mav
    )
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    junk = [
        b"", b"\x00", b"hello world", bytes(range(256)) * 4, good[:7], bytes(bad_crc),
        b"\xfd\xff" + b"\x00" * 300,  # a MAVLink 2 header claiming 255 bytes, then rubbish
        b"\xfe\x05\x00\x01\x01\xfa" + b"\x01" * 7,  # MAVLink 1 frame of an unknown message id
        struct.pack("<BBBBBBBBBB", 0xFD, 0, 0, 0, 0, 1, 1, 0xFF, 0xFF, 0xFF),  # unknown MAVLink 2 id
    ]  # fmt: skip
    for data in junk:
        gcs.raw(data)
    # Well-formed but unexpected or unusable messages.
    gcs.send(M.MAVLink_mission_count_message(1, 1, 3, 0))
    gcs.send(M.MAVLink_set_attitude_target_message(0, 1, 1, 0, [1, 0, 0, 0], 0, 0, 0, 0.5))
    nan_sp = M.MAVLink_set_position_target_local_ned_message(0, 1, 1, M.MAV_FRAME_LOCAL_NED, 0b0000_1101_1100_0111,
                                                              0, 0, 0, math.nan, 0, 0, 0, 0, 0, 0, 0)  # fmt: skip
    gcs.send(nan_sp)
    gcs.send(M.MAVLink_set_position_target_local_ned_message(0, 1, 1, M.MAV_FRAME_GLOBAL, 0, 0, 0, 0, 0, 0, 0,
                                                              0, 0, 0, 0, 0))  # fmt: skip
    gcs.send(
        M.MAVLink_command_long_message(
            42, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
        )
    )  # not us
    assert (
        gcs.command(31337) == M.MAV_RESULT_UNSUPPORTED
    )  # an unknown command is refused, not fatal
    # Still alive, still PX4, still disarmed, and none of that counted as a setpoint.
    assert (
        gcs.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION)
        == M.MAV_RESULT_ACCEPTED
    )
    hb = gcs.recv("HEARTBEAT")
    assert hb.autopilot == M.MAV_AUTOPILOT_PX4 and not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    assert sim._thread.is_alive()
    assert sim.bad_messages >= 3 and sim.unexpected_messages >= 3
    assert sim.setpoint_time == -math.inf
    assert set_mode(gcs, px4.MainMode.OFFBOARD) == M.MAV_RESULT_DENIED


def test_moving_obstacles_follow_the_envs_trajectories() -> None:
    cfg = make_config("easy")
    env = SafeNavVectorEnv(1, config=cfg, output="torch")
    env.reset(seed=7)
    obstacles = MovingObstacles(cfg, generate_world(cfg, 7), 7)
    torch.testing.assert_close(obstacles.pos[0], env.dyn_pos[0])
    for _ in range(45):  # across speed resamples (every 2 s) and new local goals
        env.step(np.zeros((1, 3), np.float32))
        obstacles.step()
    torch.testing.assert_close(obstacles.pos[0], env.dyn_pos[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(obstacles.vel[0], env.dyn_vel[0], atol=1e-5, rtol=0)


def test_collisions_are_counted_not_fatal() -> None:
    sim = SimVehicle(
        SimVehicleConfig(perception_port=-1, bind="127.0.0.1:0", connect=f"127.0.0.1:{free_port()}")
    )
    try:
        i = int(
            np.argmin(
                np.linalg.norm(
                    sim.world.pillar_xy[: sim.env_cfg.active_static] - sim.home[:2], axis=1
                )
            )
        )
        target = np.array([*sim.world.pillar_xy[i], 0.5])
        sim.armed, sim.landed, sim.main_mode, sim.sub_mode = (
            True,
            False,
            int(px4.MainMode.AUTO),
            int(px4.AutoSubMode.LOITER),
        )
        sim.pos = target - np.array([1.5, 0.0, 0.0])
        sim.hold_pos = target.copy()  # Hold pulls it straight through the pillar
        for _ in range(400):
            sim._physics(0.01)
        assert sim.stats.collisions >= 1 and sim.stats.min_clearance <= 0.0
        assert not sim.landed  # flies on: the count is what matters here
    finally:
        sim.close()
