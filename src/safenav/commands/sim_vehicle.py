"""``safenav sim-vehicle``: a simulated PX4 vehicle speaking MAVLink on loopback."""

from __future__ import annotations

import logging
import math
import signal
import sys

from safenav.cli import app


@app.command(name="sim-vehicle")
def sim_vehicle(
    preset: str = "easy",
    world_seed: int = 1,
    density: float = 1.0,
    episode: int = 0,
    start: tuple[float, float] | None = None,
    connect: str = "127.0.0.1:14540",
    bind: str = "127.0.0.1:0",
    perception_port: int = 14660,
    duration: float | None = None,
    param: tuple[str, ...] = (),
    quiet: bool = False,
) -> None:
    """Run a PX4-like multicopter on loopback UDP, driven by SafeNav-v1's dynamics and world.

    It sends to ``--connect`` (a ground station or ``safenav fly --connect udpin://...`` listens
    there; PX4 SITL's convention is port 14540) and serves depth images and tracked obstacles for
    the onboard runtime on TCP ``127.0.0.1:--perception-port`` (-1: off). The world is the
    ``--preset`` map of ``--world-seed``; the vehicle stands on the ground at ``--start X Y`` or at
    the start of test episode ``--episode``. ``--param NAME=VALUE`` sets PX4 parameters, e.g.
    ``COM_OF_LOSS_T=1.0`` or ``COM_OBL_RC_ACT=4`` (land on offboard loss; 5 = hold).

    Args:
        preset: SafeNav-v1 preset of the world (easy, medium, paper).
        world_seed: World seed (1 = the fixed test environment).
        density: Fraction of the obstacles that are active.
        episode: Test episode whose start is the takeoff point (when ``--start`` is not given).
        start: Takeoff point X Y in the world (ENU, metres).
        connect: HOST:PORT the vehicle sends MAVLink to (where the GCS / companion listens).
        bind: Local UDP HOST:PORT of the vehicle (port 0: any free port).
        perception_port: TCP port on 127.0.0.1 for perception frames (0: any free port; -1: off).
        duration: Stop after this many seconds (default: run until interrupted / SIGTERM).
        param: PX4 parameters NAME=VALUE (e.g. COM_OF_LOSS_T=0.5 COM_OBL_RC_ACT=4).
        quiet: Do not log the vehicle's events (arming, modes, collisions) to stderr.
    """
    import torch

    from safenav.deploy.sim_vehicle import SimVehicle, SimVehicleConfig

    torch.set_num_threads(1)  # one core for the autopilot loop, the rest for the others
    from safenav.common.checks import in_range, parse_hostport, parse_port
    from safenav.common.config import MAX_SEED
    from safenav.deploy.px4 import DEFAULT_PARAMS
    from safenav.envs.config import make_config
    from safenav.errors import SafenavError

    # Before the world is built and any port is bound.
    env_cfg = make_config(preset)  # ValueError for an unknown preset: exit 2
    in_range("--world-seed", world_seed, 0, MAX_SEED)
    if start is not None and not all(abs(x) < env_cfg.half for x in start):
        raise SafenavError(f"--start {start[0]} {start[1]}: the takeoff point must lie inside the "
                           f"{preset} map, |x|, |y| < {env_cfg.half:g} m")  # fmt: skip
    in_range("--density", density, 0.0, 1.0, "fraction of the obstacles")
    in_range("--episode", episode, 0, 999_999)
    parse_hostport(connect, "--connect")
    parse_hostport(bind, "--bind")
    parse_port("--perception-port", perception_port, allow=(-1,))
    if duration is not None and not duration > 0:
        raise SafenavError(f"--duration {duration}: must be > 0 seconds (omit it to run until "
                           "interrupted)")  # fmt: skip
    params = {}
    for item in param:
        name, sep, value = item.partition("=")
        try:
            params[name.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not math.isfinite(params.get(name.strip(), 0.0)):
            raise SafenavError(f"--param {item!r}: expected NAME=VALUE with a finite number")
        if name.strip() not in DEFAULT_PARAMS:
            raise SafenavError(f"--param {item!r}: the simulated vehicle has no parameter "
                               f"{name.strip()!r}; it knows {', '.join(DEFAULT_PARAMS)}")  # fmt: skip
    if not quiet:
        logging.basicConfig(
            level=logging.INFO, format="sim-vehicle: %(message)s", stream=sys.stderr
        )
    vehicle = SimVehicle(SimVehicleConfig(
        preset=preset, world_seed=world_seed, density=density, episode=episode, start=start,
        connect=connect, bind=bind, perception_port=perception_port, params=params,
    ))  # fmt: skip
    host, port = vehicle.mavlink_address
    perc = vehicle.perception_address
    print(f"sim-vehicle: PX4 (sys 1) on udp {host}:{port} -> {connect}; perception "
          f"{f'tcp {perc[0]}:{perc[1]}' if perc else 'off'}; world {preset} seed {world_seed}; "
          f"home ({vehicle.home[0]:.2f}, {vehicle.home[1]:.2f})", flush=True)  # fmt: skip

    def on_term(signum, frame):  # noqa: ARG001
        vehicle._stop.set()

    signal.signal(signal.SIGTERM, on_term)
    try:
        vehicle.run(duration=duration)
    except KeyboardInterrupt:
        pass
    finally:
        vehicle.close()
        s = vehicle.stats
        print(f"sim-vehicle: stopped; collisions {s.collisions}, min clearance {s.min_clearance:.2f} m, "
              f"flight time {s.flight_time:.1f} s, bad/unexpected messages {vehicle.bad_messages}/"
              f"{vehicle.unexpected_messages}", flush=True)  # fmt: skip
