"""PX4 conventions on MAVLink: custom flight modes and the parameters the vehicle simulator knows.

PX4 packs its flight mode into ``HEARTBEAT.custom_mode`` as ``main_mode << 16 | sub_mode << 24``
(``px4_custom_mode.h``) with ``MAV_MODE_FLAG_CUSTOM_MODE_ENABLED`` set in ``base_mode``;
``MAV_CMD_DO_SET_MODE`` carries the same numbers as ``param2`` (main) and ``param3`` (sub).
"""

from __future__ import annotations

from enum import IntEnum


class MainMode(IntEnum):
    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7


class AutoSubMode(IntEnum):
    READY = 1
    TAKEOFF = 2
    LOITER = 3  # "Hold"
    MISSION = 4
    RTL = 5
    LAND = 6


def encode_custom_mode(main: int, sub: int = 0) -> int:
    """``HEARTBEAT.custom_mode`` of a PX4 mode."""
    return (int(main) & 0xFF) << 16 | (int(sub) & 0xFF) << 24


def decode_custom_mode(custom_mode: int) -> tuple[int, int]:
    """``(main, sub)`` of a ``HEARTBEAT.custom_mode``."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


MODE_NAMES = {
    (MainMode.AUTO, AutoSubMode.TAKEOFF): "TAKEOFF",
    (MainMode.AUTO, AutoSubMode.LOITER): "HOLD",
    (MainMode.AUTO, AutoSubMode.LAND): "LAND",
    (MainMode.AUTO, AutoSubMode.RTL): "RTL",
    (MainMode.OFFBOARD, 0): "OFFBOARD",
    (MainMode.POSCTL, 0): "POSCTL",
    (MainMode.ALTCTL, 0): "ALTCTL",
    (MainMode.MANUAL, 0): "MANUAL",
}

# COM_OBL_RC_ACT (offboard loss action) values of PX4 >= 1.14 that the simulator implements.
OBL_ACT_LAND = 4
OBL_ACT_HOLD = 5

# Parameters of the simulated vehicle, PX4 names; values are the simulator's defaults.
DEFAULT_PARAMS: dict[str, float] = {
    "MIS_TAKEOFF_ALT": 2.5,  # m, takeoff altitude above home
    "MPC_TKO_SPEED": 1.5,  # m/s, takeoff climb rate
    "MPC_LAND_SPEED": 0.7,  # m/s, landing descent rate
    "MPC_XY_VEL_MAX": 12.0,  # m/s
    "MPC_Z_VEL_MAX_UP": 3.0,  # m/s
    "MPC_Z_VEL_MAX_DN": 1.5,  # m/s
    "COM_OF_LOSS_T": 0.5,  # s, offboard setpoint loss timeout
    "COM_OBL_RC_ACT": float(OBL_ACT_HOLD),  # offboard loss action: 4 Land, 5 Hold
    "COM_DISARM_LAND": 2.0,  # s, auto-disarm after landing (< 0: never)
    "COM_DISARM_PRFLT": 10.0,  # s, auto-disarm when armed on the ground without takeoff
}

__all__ = [
    "DEFAULT_PARAMS",
    "MODE_NAMES",
    "OBL_ACT_HOLD",
    "OBL_ACT_LAND",
    "AutoSubMode",
    "MainMode",
    "decode_custom_mode",
    "encode_custom_mode",
]
