"""``safenav fly``: fly an exported policy on PX4 in OFFBOARD over MAVLink (MAVSDK)."""

from __future__ import annotations

import json as jsonlib
import logging
import sys
from pathlib import Path
from typing import Annotated

import tyro

from safenav.cli import app

EXIT_ABORTED = 3


@app.command(name="fly")
def fly(
    policy: Path | None = None,
    connect: str = "udpin://127.0.0.1:14540",
    goal: tuple[float, float, float] | None = None,
    perception: str = "127.0.0.1:14660",
    rate: float = 20.0,
    shield: bool = False,
    takeoff_altitude: float = 1.5,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    link_timeout: float = 1.0,
    max_flight_time: float = 120.0,
    land: bool = True,
    json_out: Annotated[Path | None, tyro.conf.arg(name="json")] = None,
    demo: bool = False,
    checkpoint: Path = Path("checkpoints/csac-paper.pt"),
    scripted: bool = False,
    preset: str = "paper",
    episode: int = 0,
    gif: Path | None = None,
    verbose: bool = False,
) -> None:
    """Connect to PX4 (``--connect``, a MAVSDK URL), arm, take off, fly the ONNX ``--policy`` to
    ``--goal X Y Z`` (world ENU metres) in OFFBOARD with NED velocity setpoints at ``--rate`` Hz,
    then hold and land. Perception (depth images, tracked obstacles) comes from
    ``--perception HOST:PORT`` (the simulator's stream; see docs/deployment.md for real sensors).

    Watchdog: a missed control deadline or stale / invalid perception sends zero velocity; link
    loss (no telemetry for ``--link-timeout`` s) stops the flight with exit status 3.
    ``--shield`` adds the velocity-obstacle safety shield.

    ``--demo`` starts ``safenav sim-vehicle`` itself and flies test episode ``--episode`` of the
    ``--preset`` scenario with ``--checkpoint`` (exported on the fly; ``--scripted`` flies the
    scripted go-to-goal actor instead), printing a summary, writing ``--json`` and a GIF
    (``--gif``, default flight.gif).

    Args:
        policy: Exported ONNX policy (its ``.json`` sidecar next to it).
        connect: MAVSDK connection URL of the vehicle (SITL: ``udpin://0.0.0.0:14540``; serial:
            ``serial:///dev/ttyTHS1:921600``).
        goal: Goal X Y Z in the world frame (ENU, metres).
        perception: HOST:PORT of the perception stream (depth images and tracked obstacles).
        rate: Setpoint rate in Hz (>= 10; NavRL flies at 20).
        shield: Correct the policy's velocity with the velocity-obstacle safety shield.
        takeoff_altitude: Takeoff altitude above home, metres.
        origin: World ENU position of PX4's local NED origin.
        link_timeout: Seconds without telemetry that count as link loss (exit status 3).
        max_flight_time: Abort (hold and land) if the goal is not reached within this many seconds.
        land: Land at the goal (else hold there).
        json_out: Write the flight summary (JSON) here.
        demo: Start the simulated vehicle and fly a test episode (see above).
        checkpoint: Checkpoint flown by ``--demo`` (exported to ONNX on the fly).
        scripted: With ``--demo``: fly the scripted go-to-goal actor instead of a checkpoint.
        preset: With ``--demo``: SafeNav-v1 preset of the scenario.
        episode: With ``--demo``: test episode (start and goal) of the fixed scenario.
        gif: With ``--demo``: where to write the flight's GIF (default flight.gif).
        verbose: Log MAVSDK's own messages and debug output.
    """
    from safenav.deploy.fly import FlightAborted
    from safenav.errors import SafenavError

    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")  # fmt: skip
    if not verbose:
        logging.getLogger("safenav.mavsdk").setLevel(logging.WARNING)
    if rate < 10.0:
        raise SafenavError(
            f"--rate {rate} Hz is too low: PX4 offboard needs a steady setpoint stream, use >= 10 Hz"
        )
    try:
        if demo:
            from safenav.deploy.demo import run_demo

            summary = run_demo(policy=policy, checkpoint=checkpoint, scripted=scripted, preset=preset,
                               episode=episode, rate=rate, shield=shield, gif=gif or Path("flight.gif"),
                               max_flight_time=max_flight_time)  # fmt: skip
        else:
            if policy is None or goal is None:
                raise SafenavError("pass --policy policy.onnx and --goal X Y Z (or --demo)")
            summary = fly_policy(policy, connect, goal, perception, rate, shield, takeoff_altitude, origin,
                                 link_timeout, max_flight_time, land)  # fmt: skip
    except FlightAborted as err:
        summary = getattr(err, "summary", None)
        if json_out is not None and summary is not None:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(jsonlib.dumps(summary, indent=2) + "\n")
        print(f"safenav fly: aborted: {err}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_ABORTED) from None
    print(jsonlib.dumps(summary, indent=2))
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(jsonlib.dumps(summary, indent=2) + "\n")


def fly_policy(policy: Path, connect: str, goal, perception: str, rate: float, shield: bool,
               takeoff_altitude: float, origin, link_timeout: float, max_flight_time: float, land: bool) -> dict:  # fmt: skip
    import torch

    from safenav.deploy.export import OnnxPolicy, load_sidecar
    from safenav.deploy.fly import FlightAborted, FlightController, FlyConfig, MavsdkLink
    from safenav.deploy.runtime import OnboardRuntime, RuntimeConfig
    from safenav.deploy.shield import ShieldConfig
    from safenav.deploy.sim_vehicle import parse_hostport

    if not policy.exists():
        from safenav.errors import SafenavError

        raise SafenavError(
            f"{policy} not found: export one with `safenav export CHECKPOINT --onnx {policy}`"
        )
    _, cfg = load_sidecar(policy)
    torch.set_num_threads(1)  # the runtime is single-threaded by design; leave the other cores
    runtime = OnboardRuntime(OnnxPolicy(policy), cfg,
                             RuntimeConfig(shield=ShieldConfig.for_env(cfg) if shield else None))  # fmt: skip
    link = MavsdkLink(connect)
    ctl = FlightController(runtime, link, FlyConfig(
        goal=tuple(goal), rate_hz=rate, takeoff_altitude=takeoff_altitude, origin=tuple(origin),
        goal_tolerance=cfg.goal_tolerance, link_timeout_s=link_timeout, max_flight_s=max_flight_time, land=land,
    ), perception=parse_hostport(perception) if perception else None)  # fmt: skip
    try:
        return ctl.fly().summary()
    except FlightAborted as err:
        err.summary = ctl.log.summary()
        raise
    finally:
        link.close()
