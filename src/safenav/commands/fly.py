"""``safenav fly``: fly an exported policy on PX4 in OFFBOARD over MAVLink (MAVSDK)."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Annotated

import tyro

from safenav.cli import app

EXIT_ABORTED = 3
MAX_DISTANCE = 10_000.0  # m: goals and origins beyond this are typos
EXIT_COLLIDED = 4  # the flight completed but hit something (README, exit codes)


@app.command(name="fly")
def fly(
    policy: Path | None = None,
    connect: str = "udpin://127.0.0.1:14540",
    goal: tuple[float, float, float] | None = None,
    perception: str = "127.0.0.1:14660",
    rate: float = 20.0,
    shield: bool = False,
    shield_memory: int = 0,
    shield_map: bool = False,
    shield_mover_margin: float = 0.0,
    shield_brake: bool = False,
    planner_filter: bool = False,
    takeoff_altitude: float = 1.5,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    link_timeout: float = 1.0,
    max_flight_time: float = 120.0,
    land: bool = True,
    json_out: Annotated[Path | None, tyro.conf.arg(name="json")] = None,
    demo: bool = False,
    checkpoint: Path = Path("checkpoints/csac.pt"),
    scripted: bool = False,
    preset: str = "paper",
    episode: int = 0,
    gif: Path | None = None,
    record: Path | None = None,
    verbose: bool = False,
) -> None:
    """Connect to PX4 (``--connect``, a MAVSDK URL), arm, take off, fly the ONNX ``--policy`` to
    ``--goal X Y Z`` (world ENU metres) in OFFBOARD with NED velocity setpoints at ``--rate`` Hz,
    then hold and land. Perception (depth images, tracked obstacles) comes from
    ``--perception HOST:PORT`` (the simulator's stream; see docs/deployment.md for real sensors).

    Watchdog: a missed control deadline or stale / invalid perception sends zero velocity; link
    loss (no telemetry for ``--link-timeout`` s) stops the flight with exit status 3.
    ``--shield`` adds the velocity-obstacle safety shield; ``--shield-memory 20`` gives it the
    range images of the last 2 s (docs/deployment.md, "The memory shield").

    ``--demo`` starts ``safenav sim-vehicle`` itself and flies test episode ``--episode`` of the
    ``--preset`` scenario with ``--checkpoint`` (exported on the fly; ``--scripted`` flies the
    scripted go-to-goal actor instead), printing a summary, writing ``--json`` and a GIF
    (``--gif``, default flight.gif).

    ``--record flight.mcap`` logs the flight in MCAP with ROS 2 messages (pose, setpoints, range
    image, obstacles, goal) for Foxglove or ``ros2 bag`` (docs/deployment.md, "Flight logs").

    Args:
        policy: Exported ONNX policy (its ``.json`` sidecar next to it).
        connect: MAVSDK connection URL of the vehicle (SITL: ``udpin://0.0.0.0:14540``; serial:
            ``serial:///dev/ttyTHS1:921600``).
        goal: Goal X Y Z in the world frame (ENU, metres).
        perception: HOST:PORT of the perception stream (depth images and tracked obstacles).
        rate: Setpoint rate in Hz (>= 10; NavRL flies at 20).
        shield: Correct the policy's velocity with the velocity-obstacle safety shield.
        shield_memory: With --shield: its static obstacles are the range images of the last N
            env steps (0.1 s each; 20 was chosen on validation maps), placed by odometry; 0 or 1:
            the current image only.
        shield_map: With --shield: it also avoids every pillar the onboard map (built from the
            depth images) holds at the vehicle's lower extent (a level scan of the map).
        shield_mover_margin: With --shield: metres more clearance from tracked moving obstacles
            (0-2; 0.3 was chosen on validation maps).
        shield_brake: With --shield: the braking cap: near a static obstacle, the ground or the
            ceiling the shield slows the vehicle to a speed it can stop from (beyond NavRL's).
        planner_filter: After the shield (if any), the model-predictive safety filter on
            board, as safenav eval --planner-filter flies it (beyond the paper). The pillar
            planner flies where the command leaves no way out in a 2 s rollout, and for 5 s
            where the flight came less than 1 m nearer its goal over the last 5 s (the adopted
            filter, which a --flight-filter policy records). Needs a policy with
            the pillar list (static_tracked > 0).
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
        record: Log the flight here (*.mcap: ROS 2 messages, for Foxglove / ros2 bag).
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
    from safenav.commands.eval import check_shield_memory

    memory = check_shield_memory(shield, shield_memory, shield_map, shield_mover_margin,
                                 shield_brake)  # fmt: skip
    check_fly_args(policy, connect, perception, rate, takeoff_altitude, link_timeout,
                   max_flight_time, json_out, demo, preset, episode, gif, goal, origin,
                   checkpoint if demo and not scripted and policy is None else None, record)  # fmt: skip
    if planner_filter and rate > 10.0:
        print(f"note: --planner-filter at --rate {rate:g} Hz: the filter takes ~25 ms a tick on one "
              "core; at 20 Hz on a loaded 2-core machine it missed 8 % of the deadlines "
              "(docs/deployment.md, \"The planner filter on board\"): --rate 10 is the env's "
              "control rate", file=sys.stderr)  # fmt: skip
    try:
        if demo:
            from safenav.deploy.demo import run_demo

            summary = run_demo(policy=policy, checkpoint=checkpoint, scripted=scripted, preset=preset,
                               episode=episode, rate=rate, shield=shield, shield_memory=memory, shield_map=shield_map, shield_mover_margin=shield_mover_margin, shield_brake=shield_brake, gif=gif or Path("flight.gif"),
                               max_flight_time=max_flight_time, record=record,
                               planner_filter=planner_filter)  # fmt: skip
        else:
            if policy is None or goal is None:
                raise SafenavError("pass --policy policy.onnx and --goal X Y Z (or --demo)")
            summary = fly_policy(policy, connect, goal, perception, rate, shield, takeoff_altitude, origin,
                                 link_timeout, max_flight_time, land, record=record,
                                 shield_memory=memory, shield_map=shield_map,
                                 shield_mover_margin=shield_mover_margin,
                                 shield_brake=shield_brake, planner_filter=planner_filter)  # fmt: skip
    except FlightAborted as err:
        summary = getattr(err, "summary", None)
        if json_out is not None and summary is not None:
            from safenav.common.jsonout import write_json

            write_json(json_out, {**summary, "outcome": "aborted"})
        known = summary or {}
        so_far = (f" ({known['collisions']} collision{'s' if known['collisions'] != 1 else ''}, "
                  f"min clearance {known.get('min_clearance_m')} m)"
                  if known.get("collisions") is not None else "")  # fmt: skip
        gif_note = f"; flight GIF {known['gif']}" if known.get("gif") else ""
        print(f"safenav fly: aborted: {err}{so_far}{gif_note}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_ABORTED) from None
    from safenav.common.jsonout import dumps, write_json

    summary = {**summary, "outcome": outcome(summary)}
    print(dumps(summary), end="")
    if json_out is not None:
        write_json(json_out, summary)
    print(f"safenav fly: {describe_flight(summary)}", file=sys.stderr, flush=True)
    if summary["outcome"] == "collided":
        raise SystemExit(EXIT_COLLIDED)


def outcome(summary: dict) -> str:
    """``collided`` (any collision, goal reached or not: the env ends an episode at its first
    one), ``reached_goal``, or ``not_reached``."""
    if (summary.get("collisions") or 0) > 0:
        return "collided"
    return "reached_goal" if summary.get("reached_goal") else "not_reached"


def describe_flight(summary: dict) -> str:
    """One line: the outcome with the collisions and the minimum clearance (when known)."""
    reached = "reached the goal" if summary.get("reached_goal") else "did not reach the goal"
    text = f"{reached} after {summary.get('flight_time_s', 0.0):.1f} s"
    collisions, clearance = summary.get("collisions"), summary.get("min_clearance_m")
    if collisions is None:
        text += "; collisions unknown (the perception stream reports no ground truth)"
    else:
        text += f"; {collisions} collision{'s' if collisions != 1 else ''}"
    if clearance is not None:
        text += f", min clearance {clearance:.2f} m"
    return text + (
        f" (exit {EXIT_COLLIDED}: the flight collided)" if outcome(summary) == "collided" else ""
    )


def check_fly_args(policy: Path | None, connect: str, perception: str, rate: float,
                   takeoff_altitude: float, link_timeout: float, max_flight_time: float,
                   json_out: Path | None, demo: bool, preset: str, episode: int,
                   gif: Path | None, goal=None, origin=(0.0, 0.0, 0.0),
                   checkpoint: Path | None = None, record: Path | None = None) -> None:  # fmt: skip
    """Refuse bad values before connecting to anything."""
    from safenav.common.checks import (
        at_least,
        check_output_file,
        in_range,
        parse_hostport,
    )
    from safenav.errors import SafenavError

    in_range("--rate", rate, 10.0, 200.0, "Hz")
    in_range("--takeoff-altitude", takeoff_altitude, 0.1, 100.0, "metres above home")
    in_range("--link-timeout", link_timeout, 0.05, 60.0, "seconds")
    at_least("--max-flight-time", max_flight_time, 1.0, "seconds")
    if goal is not None:
        if not goal[2] > 0:
            raise SafenavError(f"--goal {' '.join(map(str, goal))}: Z is the goal's altitude "
                               "(ENU, metres): it must be > 0")  # fmt: skip
        if max(map(abs, goal)) > MAX_DISTANCE:
            raise SafenavError(f"--goal {' '.join(map(str, goal))}: more than {MAX_DISTANCE:g} m "
                               "from the origin")  # fmt: skip
    if max(map(abs, origin)) > MAX_DISTANCE:
        raise SafenavError(f"--origin {' '.join(map(str, origin))}: more than {MAX_DISTANCE:g} m "
                           "from the world origin")  # fmt: skip
    if perception:
        parse_hostport(perception, "--perception")
    if json_out is not None:
        check_output_file(json_out, "--json", "flight.json")
    if record is not None:
        from safenav.deploy.mcap_log import check_record_path

        check_record_path(record, "--record")
    if policy is not None:
        from safenav.deploy.export import is_torch_file

        onnx = policy if policy.suffix.lower() == ".onnx" else policy.with_suffix(".onnx")
        if not policy.exists():
            raise SafenavError(f"--policy {policy} not found: export one with `safenav export "
                               f"CHECKPOINT --onnx {onnx}`")  # fmt: skip
        if policy.is_dir():
            raise SafenavError(f"--policy {policy} is a directory, not an exported policy.onnx")
        if policy.suffix.lower() != ".onnx" or is_torch_file(policy):
            # the fix names a new .onnx file: never one that would overwrite the checkpoint
            raise SafenavError(f"--policy {policy} is not an exported ONNX policy: export it with "
                               f"`safenav export {policy} --onnx {onnx}` and fly that")  # fmt: skip
    if checkpoint is not None and not checkpoint.is_file():
        raise SafenavError(f"--checkpoint {checkpoint} not found: train one (safenav train), pass "
                           "--policy policy.onnx, or fly --scripted")  # fmt: skip
    if demo:
        from safenav.envs.config import make_config

        make_config(preset)  # ValueError for an unknown preset: exit 2
        in_range("--episode", episode, 0, 999_999)
        gif = gif or Path("flight.gif")
        check_output_file(gif, "--gif", "flight.gif")
        if gif.suffix.lower() != ".gif":
            raise SafenavError(f"--gif {gif}: name the GIF *.gif")
    # Last: it probes the port (a busy one is exit 1), after every mistake in the command line.
    check_connect_url(connect)


def check_connect_url(url: str) -> None:
    """A MAVSDK connection URL: ``udpin://HOST:PORT``, ``udpout://``, ``tcpin://``, ``tcpout://``
    (also the older ``udp://``, ``tcp://``) or ``serial://DEVICE[:BAUD]``."""
    from safenav.common.checks import parse_hostport
    from safenav.errors import SafenavError

    scheme, sep, _ = url.partition("://")
    if not sep or scheme not in ("udp", "udpin", "udpout", "tcp", "tcpin", "tcpout", "serial"):
        raise SafenavError(f"--connect {url!r}: expected a MAVSDK URL such as "
                           "udpin://127.0.0.1:14540 or serial:///dev/ttyTHS1:921600")  # fmt: skip
    if scheme == "serial":
        return
    host, port = parse_hostport(url, "--connect")
    if scheme in ("udpin", "udp", "tcpin") and port != 0:  # we listen there: is it free?
        import errno
        import socket

        from safenav.errors import SafenavRuntimeError

        kind = socket.SOCK_STREAM if scheme == "tcpin" else socket.SOCK_DGRAM
        with socket.socket(socket.AF_INET, kind) as probe:
            try:
                probe.bind((host if host not in ("", "0.0.0.0") else "0.0.0.0", port))
            except OSError as err:
                if err.errno == errno.EADDRINUSE:
                    raise SafenavRuntimeError(f"--connect {url}: port {port} is already in use "
                                              "(another fly, a ground station?)") from None  # fmt: skip
                raise SafenavError(f"--connect {url}: cannot listen there "
                                   f"({err.strerror or err})") from None  # fmt: skip


def fly_policy(policy: Path, connect: str, goal, perception: str, rate: float, shield: bool,
               takeoff_altitude: float, origin, link_timeout: float, max_flight_time: float, land: bool,
               record: Path | None = None, shield_memory: int | None = None,
               shield_map: bool = False, shield_mover_margin: float = 0.0,
               shield_brake: bool = False, planner_filter: bool = False) -> dict:  # fmt: skip
    """Fly ``policy`` to ``goal`` on the vehicle at ``connect``; ``shield_memory``: the shield's
    memory in range images (default: 1 with ``shield``, the memoryless shield);
    ``planner_filter``: the planner filter after it."""
    import torch

    from safenav.common.checks import parse_hostport
    from safenav.deploy.export import OnnxPolicy, load_sidecar
    from safenav.deploy.fly import FlightAborted, FlightController, FlyConfig, MavsdkLink
    from safenav.deploy.onboard_filter import check_planner_filter
    from safenav.deploy.runtime import OnboardRuntime, RuntimeConfig

    _, cfg = load_sidecar(policy)  # refuses a checkpoint given as --policy, with the fix
    check_planner_filter(planner_filter, cfg, str(policy))
    torch.set_num_threads(1)  # the runtime is single-threaded by design; leave the other cores
    memory = max(1, shield_memory or 1) if shield else 0  # range images; 0: no shield
    runtime = OnboardRuntime(OnnxPolicy(policy), cfg,
                             RuntimeConfig.for_flight(cfg, memory, rate, shield_map and shield,
                                                      shield_mover_margin if shield else 0.0,
                                                      shield_brake and shield,
                                                      planner_filter))  # fmt: skip
    recorder = None
    if record is not None:  # no ground truth here: the map holds the goal and the geofence
        from safenav.deploy.mcap_log import McapRecorder, Scene

        recorder = McapRecorder(record, Scene.for_env(cfg, goal, arena=runtime.config.geofence),
                                metadata={"verb": "fly", "policy": str(policy), "connect": connect,
                                          "rate_hz": rate, "shield": shield, "shield_memory": memory,
                                          "shield_map": shield_map,
                                          "shield_mover_margin": shield_mover_margin,
                                          "shield_brake": shield_brake,
                                          "planner_filter": planner_filter})  # fmt: skip
    link = MavsdkLink(connect)
    ctl = FlightController(runtime, link, FlyConfig(
        goal=tuple(goal), rate_hz=rate, takeoff_altitude=takeoff_altitude, origin=tuple(origin),
        goal_tolerance=cfg.goal_tolerance, link_timeout_s=link_timeout, max_flight_s=max_flight_time, land=land,
    ), perception=parse_hostport(perception, "--perception") if perception else None,
        recorder=recorder)  # fmt: skip
    try:
        summary = ctl.fly().summary()
    except FlightAborted as err:
        err.summary = ctl.log.summary()
        raise
    finally:
        link.close()
        if recorder is not None:
            recorder.close()  # never raises: a failure is in recorder.error
    if recorder is not None:
        summary["record"] = str(record)
        if recorder.error:
            summary["record_error"] = recorder.error
    return summary
