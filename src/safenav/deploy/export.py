"""Export the deterministic actor to ONNX with a JSON sidecar of its conventions, and run it.

The sidecar (``policy.onnx.json`` next to ``policy.onnx``) is everything a runtime needs besides
the network: the observation layout and scaling, the action scaling and frame, ``v_max``, the
rate the policy was trained at, and the full env configuration (:class:`EnvConfig`).

Inputs of the ONNX graph (batch dimension ``N`` dynamic, float32): ``state (N, 8)``, ``lidar (N, 4,
36)`` (``(N, 8, 36)`` with a memory image, ``lidar_memory``), ``dynamic (N, 5, 10)``, and
``static (N, K, 7)`` only for a policy with a pillar list (``static_tracked`` K > 0; the others
keep their three inputs); output ``action (N, 3)`` in ``[-1, 1]``, the goal-frame velocity
divided by ``v_max``. Exported with the TorchScript-based exporter (``dynamo=False``): one static
graph, no onnxscript rewriting, identical on every torch version that still ships it; the dynamo
exporter is the fallback.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from safenav.common.atomic import replace_synced
from safenav.common.jsonout import write_json
from safenav.envs.config import EnvConfig, observation_shapes
from safenav.envs.nav import DIST_SCALE, Z_SCALE
from safenav.errors import SafenavError, one_line
from safenav.nn.networks import STATIC_KEY, input_order

SIDECAR_FORMAT = "safenav-policy/1"
INPUT_NAMES = ("state", "lidar", "dynamic")
"""The inputs of every exported policy; one with a pillar list has ``static`` after them
(:func:`input_names`)."""
OUTPUT_NAME = "action"


def input_names(cfg: EnvConfig) -> tuple[str, ...]:
    """The ONNX inputs of a policy of env configuration ``cfg``, in the actor's positional order
    (:func:`safenav.nn.networks.input_order`): :data:`INPUT_NAMES`, then ``static`` with
    ``static_tracked`` > 0."""
    return input_order(observation_shapes(cfg))


def sidecar_path(onnx_path: str | Path) -> Path:
    p = Path(onnx_path)
    return p.with_name(p.name + ".json")


def policy_conventions(cfg: EnvConfig) -> dict[str, Any]:
    """The observation and action conventions of SafeNav-v1, as written into the sidecar."""
    return {
        "observation": {
            "state": {
                "shape": [8],
                "layout": ["unit_to_goal_x", "unit_to_goal_y", "unit_to_goal_z",
                           "horizontal_distance_to_goal", "z_distance_to_goal",
                           "velocity_x", "velocity_y", "velocity_z"],
                "frame": "goal",
                "scale": {"horizontal_distance_to_goal_m": DIST_SCALE, "z_distance_to_goal_m": Z_SCALE,
                          "velocity_m_s": cfg.v_max},
            },
            "lidar": {
                "shape": list(observation_shapes(cfg)["lidar"]),
                "value": "(range - min(hit_distance, range)) / range",
                "range_m": cfg.lidar_range,
                "rows_elevation_deg": list(cfg.lidar_v_angles),
                "columns_azimuth_deg": [360.0 * j / cfg.lidar_h_beams for j in range(cfg.lidar_h_beams)],
                "azimuth_zero": "goal-frame x (toward the goal), counter-clockwise",
                "grid_resolution_m": cfg.grid_resolution,
                **({"memory_rows": {
                    "rows": [len(cfg.lidar_v_angles), 2 * len(cfg.lidar_v_angles)],
                    "control_steps": cfg.lidar_memory,
                    "value": "per cell the nearest beam hit of the last control_steps range "
                             "images (the current one included), kept in the world by odometry "
                             "and seen from the current position: (range - d) / range",
                    "forget": "when a new goal is set",
                }} if cfg.lidar_memory else {}),
            },
            "dynamic": {
                "shape": [cfg.num_tracked, 10],
                "layout": ["unit_rel_x", "unit_rel_y", "unit_rel_z", "horizontal_distance",
                           "z_distance", "velocity_x", "velocity_y", "velocity_z", "width_class",
                           "is_cuboid"],
                "frame": "goal",
                "scale": {"distance_m": cfg.lidar_range, "velocity_m_s": cfg.v_max},
                "rows": f"the {cfg.num_tracked} horizontally nearest moving obstacles within "
                        f"{cfg.lidar_range} m, nearest first; zero rows beyond",
            },
            **({"static": {
                "shape": [cfg.static_tracked, 7],
                "layout": ["near_rel_x", "near_rel_y", "centre_rel_x", "centre_rel_y",
                           "half_side", "top_minus_altitude", "present"],
                "frame": "goal",
                "scale": {"rel_m": cfg.lidar_range, "half_side_m": 0.4,
                          "top_minus_altitude_m": cfg.lidar_range},
                "rows": f"the {cfg.static_tracked} pillars nearest by clearance (3-D distance to "
                        f"the ground-standing box) within {cfg.lidar_range} m, nearest first; "
                        "zero rows beyond",
                "source": "the onboard height map: each 4-connected group of occupied cells "
                          "(above the ground, not the geofence wall) one footprint, its bounding "
                          "box as a square of the larger half side, its tallest column "
                          "(safenav.envs.sensors.map_footprints; static_source "
                          f"{cfg.static_source!r} in training)",
            }} if cfg.static_tracked else {}),
        },
        "action": {
            "shape": [3], "range": [-1.0, 1.0], "frame": "goal", "scale_m_s": cfg.v_max,
            "meaning": "velocity command = action * v_max per goal-frame axis (x toward the goal, z up)",
        },
        "goal_frame": "x from start to goal with z zeroed, z up; yaw fixed when the goal is set",
        "v_max": cfg.v_max,
        "control_hz": cfg.control_hz,
    }  # fmt: skip


def check_deployable(cfg: EnvConfig, where: str | Path) -> None:
    """``SafenavError`` unless the onboard runtime can build the observations of a policy of env
    configuration ``cfg`` (``where`` names it): not for a range-image history yet (a memory image,
    ``lidar_memory``, it builds; a pillar list, ``static_tracked``, it builds from its map as the
    env's ``static_source="map"`` does)."""
    if cfg.lidar_history > 1:
        raise SafenavError(f"{where}: policies trained with lidar_history > 1 cannot be deployed "
                           f"yet: this one reads the range images of the last {cfg.lidar_history} "
                           "control steps, and the onboard runtime (safenav export / fly) builds "
                           "the current one only; evaluate it in simulation (safenav eval)")  # fmt: skip


def call_actor(
    actor: nn.Module,
    state: torch.Tensor,
    lidar: torch.Tensor,
    dynamic: torch.Tensor,
    static: torch.Tensor | None = None,
) -> torch.Tensor:
    """Call an actor with the observation tensors in its own positional order: the trainer's
    ``DeterministicActor`` names it in ``input_names``; otherwise ``(state, lidar, dynamic)``,
    then ``static`` when given (a policy with a pillar list, ``static_tracked``)."""
    names = getattr(actor, "input_names", None)
    if names is None:
        return (
            actor(state, lidar, dynamic) if static is None else actor(state, lidar, dynamic, static)
        )
    named = {"state": state, "lidar": lidar, "dynamic": dynamic}
    if static is not None:
        named[STATIC_KEY] = static
    unknown = sorted(set(names) - set(named))
    if unknown == [STATIC_KEY]:
        raise SafenavError("the actor reads a pillar list (static), but none was given: its env "
                           "configuration has static_tracked 0")  # fmt: skip
    if unknown:
        raise SafenavError(
            f"the actor reads observation entries {unknown}: not a SafeNav-v1 policy"
        )
    return actor(*(named[k] for k in names))


class NamedInputActor(nn.Module):
    """Named-input wrapper: ``forward(state, lidar, dynamic[, static]) -> action`` clamped to
    [-1, 1] (``static`` for a policy with a pillar list only)."""

    def __init__(self, actor: nn.Module) -> None:
        super().__init__()
        self.actor = actor

    def forward(
        self,
        state: torch.Tensor,
        lidar: torch.Tensor,
        dynamic: torch.Tensor,
        static: torch.Tensor | None = None,
    ) -> torch.Tensor:
        return torch.clamp(call_actor(self.actor, state, lidar, dynamic, static), -1.0, 1.0)


def random_observations(cfg: EnvConfig, n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random observations spanning the env's value ranges (for export checks); ``static`` too
    for a policy with a pillar list (drawn last: the other entries are those of any policy)."""
    g = torch.Generator().manual_seed(seed)
    shapes = observation_shapes(cfg)
    state = torch.rand(n, *shapes["state"], generator=g) * 2 - 1
    lidar = torch.rand(n, *shapes["lidar"], generator=g)
    dynamic = torch.rand(n, *shapes["dynamic"], generator=g) * 2 - 1
    obs = {"state": state, "lidar": lidar, "dynamic": dynamic}
    if STATIC_KEY in shapes:  # positions, sizes and tops in [-1, 1]; the presence flag 0 or 1
        static = torch.rand(n, *shapes[STATIC_KEY], generator=g) * 2 - 1
        static[..., -1] = (static[..., -1] > 0).float()
        obs[STATIC_KEY] = static
    return obs


def export_onnx(
    actor: nn.Module,
    cfg: EnvConfig,
    onnx_path: str | Path,
    *,
    opset: int = 17,
    checkpoint: str | None = None,
    check_observations: dict[str, torch.Tensor] | None = None,
    atol: float = 1e-5,
) -> dict[str, Any]:
    """Write ``onnx_path`` and its sidecar; check ONNX Runtime against torch within ``atol`` on
    random observations (and ``check_observations``, e.g. real ones from the env).

    The model is written at exactly ``opset`` or not at all (``SafenavError`` naming the reason):
    the exporters write into a temporary file that replaces ``onnx_path`` only after its opset and
    the ONNX Runtime check passed, so a failed export leaves an existing file as it was.

    Returns the sidecar dict (with ``"check"``: the largest absolute difference found).
    """
    import onnx

    check_deployable(cfg, checkpoint or onnx_path)
    onnx_path = Path(onnx_path)
    newest = onnx.defs.onnx_opset_version()
    if not 1 <= opset <= newest:
        raise SafenavError(f"--opset {opset}: ONNX opsets run from 1 to {newest} (this onnx); "
                           "the default is 17")  # fmt: skip
    onnx_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = onnx_path.with_name(f".{onnx_path.name}.{os.getpid()}.tmp")
    try:
        exporter = _export(actor, cfg, tmp, opset)
        written = next((o.version for o in onnx.load(str(tmp)).opset_import if o.domain in ("", "ai.onnx")),
                       None)  # fmt: skip
        if written != opset:
            raise SafenavError(f"--opset {opset}: the {exporter} exporter wrote opset {written} for "
                               f"this policy, not {opset}: ask for opset {written} or higher")  # fmt: skip
        worst = _check_onnx_runtime(actor, cfg, tmp, check_observations)
        if not worst <= atol:
            raise SafenavError(
                f"ONNX export of {onnx_path} differs from torch by {worst:.2e} > {atol:.0e}"
            )
        sidecar = {
            "format": SIDECAR_FORMAT,
            "onnx": onnx_path.name,
            "sha256": hashlib.sha256(tmp.read_bytes()).hexdigest(),
            "inputs": list(input_names(cfg)),
            "output": OUTPUT_NAME,
            "opset": written,
            "exporter": exporter,
            "checkpoint": checkpoint,
            **policy_conventions(cfg),
            "env_config": dataclasses.asdict(cfg),
            "check": {"max_abs_diff": worst, "atol": atol},
        }
        replace_synced(tmp, onnx_path)  # fsync, rename, fsync of the directory
    finally:
        tmp.unlink(missing_ok=True)
    write_json(sidecar_path(onnx_path), sidecar)
    return sidecar


def _export(actor: nn.Module, cfg: EnvConfig, path: Path, opset: int) -> str:
    """Export ``actor`` to ``path`` at ``opset``; returns the exporter used. The TorchScript
    exporter first; the dynamo exporter only when that one is gone, never as a silent way around
    an opset the TorchScript exporter refused."""
    model = NamedInputActor(actor).eval().to("cpu")
    names = input_names(cfg)
    example = random_observations(cfg, 2)
    args = tuple(example[k] for k in names)
    axes = {k: {0: "batch"} for k in (*names, OUTPUT_NAME)}
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            with _stdout_silenced():  # a failing TorchScript export prints its graph (C++)
                torch.onnx.export(model, args, str(path), input_names=list(names),
                                  output_names=[OUTPUT_NAME], dynamic_axes=axes,
                                  opset_version=opset, dynamo=False)  # fmt: skip
            return "torchscript"
        except Exception as err:  # noqa: BLE001 -- the legacy exporter may be gone: use dynamo
            if "opset" in str(err).lower():  # the opset is the problem, not the exporter
                reason = one_line(str(err).split(". ")[0], 160)
                raise SafenavError(f"--opset {opset}: this policy cannot be exported at opset "
                                   f"{opset} ({reason}); the default is 17") from None  # fmt: skip
        batch = torch.export.Dim("batch", min=1)
        try:
            torch.onnx.export(model, args, str(path), input_names=list(names),
                              output_names=[OUTPUT_NAME], opset_version=opset, dynamo=True,
                              dynamic_shapes={k: {0: batch} for k in names},
                              external_data=False)  # fmt: skip
        except Exception as err:  # noqa: BLE001 -- one line, naming the opset
            raise SafenavError(f"--opset {opset}: the ONNX export failed "
                               f"({type(err).__name__}: {one_line(err, 160)})") from None  # fmt: skip
        return "dynamo"


@contextlib.contextmanager
def _stdout_silenced():
    """File descriptor 1 to /dev/null for the block (output printed by C++ too)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _check_onnx_runtime(actor: nn.Module, cfg: EnvConfig, path: Path,
                        check_observations: dict[str, Any] | None) -> float:  # fmt: skip
    """Largest |ONNX Runtime - torch| over random (and the given) observations."""
    model = NamedInputActor(actor).eval().to("cpu")
    try:
        runner = OnnxPolicy(path)
    except Exception as err:  # noqa: BLE001 -- e.g. an opset this onnxruntime does not run
        raise SafenavError(f"ONNX Runtime cannot load the exported model "
                           f"({type(err).__name__}: {one_line(err, 200)})") from None  # fmt: skip
    sets = [random_observations(cfg, 64, seed=1)]
    if check_observations is not None:
        sets.append(
            {k: torch.as_tensor(v, dtype=torch.float32) for k, v in check_observations.items()}
        )
    names = input_names(cfg)
    worst = 0.0
    for obs in sets:
        with torch.no_grad():
            ref = model(*(obs[k] for k in names)).numpy()
        got = runner(*(obs[k].numpy() for k in names))
        worst = max(worst, float(np.abs(got - ref).max()))
    return worst


def load_sidecar(onnx_path: str | Path) -> tuple[dict[str, Any], EnvConfig]:
    """The sidecar of ``onnx_path`` and its env configuration."""
    path = sidecar_path(onnx_path)
    if Path(onnx_path).suffix.lower() != ".onnx" or is_torch_file(onnx_path):
        onnx = Path(onnx_path).with_suffix(".onnx")
        raise SafenavError(f"{onnx_path} is not an exported ONNX policy: export it first with "
                           f"`safenav export {onnx_path} --onnx {onnx}` and fly that")  # fmt: skip
    if not path.exists():
        raise SafenavError(f"{path} (the sidecar of {onnx_path}) not found: export the policy "
                           f"again with `safenav export CHECKPOINT --onnx {onnx_path}`")  # fmt: skip
    meta = json.loads(path.read_text())
    if meta.get("format") != SIDECAR_FORMAT:
        raise SafenavError(
            f"{path} is not a {SIDECAR_FORMAT} sidecar (format={meta.get('format')!r})"
        )
    cfg = env_config_from_dict(meta["env_config"])
    check_deployable(cfg, onnx_path)
    return meta, cfg


def is_torch_file(path: str | Path) -> bool:
    """True for a file torch.save wrote (a zip archive), e.g. a training checkpoint."""
    try:
        with open(path, "rb") as f:
            return f.read(4) == b"PK\x03\x04"
    except OSError:
        return False


def env_config_from_dict(d: dict[str, Any]) -> EnvConfig:
    known = {f.name for f in dataclasses.fields(EnvConfig)}
    kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in known}
    return EnvConfig(**kwargs)


class OnnxPolicy:
    """ONNX Runtime inference of an exported actor on the CPU (``threads`` intra-op threads):
    ``(state, lidar, dynamic[, static]) -> action``, ``static`` for (and only for) a policy with a
    pillar list (its graph has that input; ``input_names``)."""

    def __init__(self, onnx_path: str | Path, threads: int = 1) -> None:
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        self.session = ort.InferenceSession(
            str(onnx_path), sess_options=opts, providers=["CPUExecutionProvider"]
        )
        self.path = Path(onnx_path)
        self.input_names = tuple(i.name for i in self.session.get_inputs())

    def __call__(self, state: np.ndarray, lidar: np.ndarray, dynamic: np.ndarray,
                 static: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        feeds = {"state": np.ascontiguousarray(state, dtype=np.float32),
                 "lidar": np.ascontiguousarray(lidar, dtype=np.float32),
                 "dynamic": np.ascontiguousarray(dynamic, dtype=np.float32)}  # fmt: skip
        if static is not None:
            feeds[STATIC_KEY] = np.ascontiguousarray(static, dtype=np.float32)
        if set(feeds) != set(self.input_names):  # ONNX Runtime's own message names no fix
            raise ValueError(f"{self.path} takes the inputs {list(self.input_names)}, given "
                             f"{list(feeds)}")  # fmt: skip
        return self.session.run(None, feeds)[0]


class TorchPolicy:
    """Torch inference of an actor module (eager or TorchScript), same call as :class:`OnnxPolicy`."""

    def __init__(self, actor: nn.Module) -> None:
        self.actor = actor.eval()

    def __call__(self, state: np.ndarray, lidar: np.ndarray, dynamic: np.ndarray,
                 static: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        as_tensor = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float32))  # noqa: E731
        with torch.inference_mode():
            out = call_actor(self.actor, as_tensor(state), as_tensor(lidar), as_tensor(dynamic),
                             None if static is None else as_tensor(static))  # fmt: skip
        return torch.clamp(out, -1.0, 1.0).numpy()


def _meta_env_config(meta: Any) -> EnvConfig | None:
    if isinstance(meta, EnvConfig):
        return meta
    candidates = []
    if isinstance(meta, dict):
        candidates = [meta.get(k) for k in ("env_config", "env", "config", "env_cfg")] + [meta]
    else:
        candidates = [getattr(meta, k, None) for k in ("env_config", "env", "config", "env_cfg")]
    for c in candidates:
        if isinstance(c, EnvConfig):
            return c
        if isinstance(c, dict):
            inner = c.get("env") if isinstance(c.get("env"), dict) else c
            if any(k in inner for k in ("map_size", "v_max", "lidar_range")):
                return env_config_from_dict(inner)
    return None


def load_actor(checkpoint: str | Path, device: str = "cpu") -> tuple[nn.Module, EnvConfig]:
    """The deterministic actor of a training checkpoint and its env configuration, through
    ``safenav.algos.policy.load_policy``."""
    path = Path(checkpoint)
    if not path.exists():
        raise SafenavError(f"checkpoint {path} not found")
    try:
        from safenav.algos.policy import load_policy  # type: ignore[import-not-found]
    except ImportError as err:
        raise SafenavError(
            f"cannot read {path}: safenav.algos.policy.load_policy is not available in this install ({err})"
        ) from None
    policy = load_policy(str(path), device=device)
    cfg = None
    if callable(getattr(policy, "env_config", None)):
        cfg = policy.env_config()
        cfg = cfg if isinstance(cfg, EnvConfig) else _meta_env_config(cfg)
    if cfg is None:
        cfg = _meta_env_config(getattr(policy, "meta", None))
    if cfg is None:
        raise SafenavError(f"{path}: the checkpoint's metadata carries no env configuration")
    check_deployable(cfg, path)
    return policy.actor, cfg


__all__ = [
    "INPUT_NAMES",
    "NamedInputActor",
    "call_actor",
    "check_deployable",
    "OUTPUT_NAME",
    "SIDECAR_FORMAT",
    "OnnxPolicy",
    "TorchPolicy",
    "env_config_from_dict",
    "export_onnx",
    "input_names",
    "is_torch_file",
    "load_actor",
    "load_sidecar",
    "observation_shapes",
    "policy_conventions",
    "random_observations",
    "sidecar_path",
]
