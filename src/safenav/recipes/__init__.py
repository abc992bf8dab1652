"""Training recipes: named, versioned sets of hyperparameters, one TOML file each.

``safenav train --config NAME|PATH`` starts from a recipe (a file shipped here, or a user's own
by path); command-line flags override it; ``config.json`` records the resolved values and the
recipe's name. Without ``--config``, ``--algo A`` on SafeNav takes the recipe named ``A`` (with
``_`` read as ``-``) when one ships, and on a Gymnasium env its task family's (``classic-sac``,
``box2d-ppo``, ``mujoco-sac``, ...; ``gym-sac`` / ``gym-ppo`` for any other env). A file's header
(its leading ``#`` comments) says where its values come from, how it departs from the paper's
equations, and what it measured.

Layout of a recipe file::

    [recipe]
    algo = "csac"          # the --algo it trains (required)
    algos = ["csac"]       # optional: every --algo it may train (default: [algo])
    base = "csac-paper"    # optional: start from another recipe, then apply this file
    [run]                  # RunConfig fields (--num-envs, --total-steps, --density.*, ...)
    num_envs = 256
    [csac]                 # CSACConfig fields (or [ppo]: PPOConfig), nested tables for sub-configs
    actor_lr = 3e-4
    [csac.curriculum]
    d_min = 0.05
    [envs."Pendulum-v1".csac]  # optional: values for one env id (or its name without -vN)
    actor_lr = 1e-3
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from safenav.common.families import PPO_ALGOS, task_family
from safenav.errors import SafenavError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

SECTIONS = ("run", "csac", "ppo")


@dataclass(frozen=True)
class Recipe:
    """A resolved recipe: its name, the algorithm, and field overrides per config section."""

    name: str
    algo: str
    sections: dict[str, dict[str, Any]] = field(default_factory=dict)
    header: str = ""
    source: str = ""
    algos: tuple[str, ...] = ()
    envs: dict[str, dict[str, dict[str, Any]]] = field(default_factory=dict)

    def section(self, name: str, env: str | None = None) -> dict[str, Any]:
        """The recipe's values of config section ``name``; with ``env``, those of its
        ``[envs."NAME"]`` table (the id without its version first, then the exact id) on top."""
        out = self.sections.get(name, {})
        if env is not None:
            env = env.split(":")[-1]
            for key in dict.fromkeys((env.rsplit("-v", 1)[0], env)):
                out = _merge(out, self.envs.get(key, {}).get(name, {}))
        return out


def available() -> list[str]:
    """Names of the recipes shipped with safenav."""
    return sorted(
        p.name[:-5] for p in resources.files(__name__).iterdir() if p.name.endswith(".toml")
    )


def default_recipe(algo: str, env_id: str) -> str | None:
    """The recipe ``--algo algo`` takes on ``env_id`` without ``--config`` (None: none ships)."""
    family, _ = task_family(env_id)
    if family == "safenav":
        name = algo.replace("_", "-")
    else:
        name = f"{family}-{'ppo' if algo in PPO_ALGOS else 'sac'}"
    return name if name in available() else None


def _read(name_or_path: str) -> tuple[dict[str, Any], str, str, str]:
    path = Path(name_or_path)
    if name_or_path.endswith(".toml") or path.exists():
        if not path.is_file():
            raise SafenavError(f"--config {name_or_path}: no such recipe file")
        text, name, source = path.read_text(), path.stem, str(path)
    else:
        shipped = resources.files(__name__) / f"{name_or_path}.toml"
        if not shipped.is_file():
            raise SafenavError(f"--config {name_or_path}: unknown recipe; shipped: {', '.join(available())} "
                               "(or give a path to a .toml file)")  # fmt: skip
        text, name, source = (
            shipped.read_text(),
            name_or_path,
            f"safenav/recipes/{name_or_path}.toml",
        )
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SafenavError(f"--config {name_or_path}: not valid TOML ({err})") from None
    header = "\n".join(line[1:].strip() for line in text.splitlines() if line.startswith("#"))
    return data, name, source, header.split("\n\n")[0] if header else ""


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_recipe(name_or_path: str, _seen: tuple[str, ...] = ()) -> Recipe:
    """The recipe ``name_or_path`` (a shipped name or a ``.toml`` path), its ``base`` applied
    first; ``SafenavError`` for unknown names, bad TOML, unknown sections or a cycle."""
    if name_or_path in _seen:
        raise SafenavError(f"--config: recipes {' -> '.join((*_seen, name_or_path))} form a cycle")
    data, name, source, header = _read(name_or_path)
    meta = data.pop("recipe", None)
    if not isinstance(meta, dict) or not isinstance(meta.get("algo"), str):
        raise SafenavError(f'{source}: a recipe needs a [recipe] table with algo = "..."')
    algos = meta.get("algos", [meta["algo"]])
    if not isinstance(algos, list) or meta["algo"] not in algos:
        raise SafenavError(f"{source}: [recipe] algos must be a list that holds algo")
    sections: dict[str, dict[str, Any]] = {}
    envs: dict[str, dict[str, dict[str, Any]]] = {}
    if "base" in meta:
        base = load_recipe(str(meta["base"]), (*_seen, name_or_path))
        sections = {k: dict(v) for k, v in base.sections.items()}
        envs = {k: dict(v) for k, v in base.envs.items()}
    env_tables = data.pop("envs", {})
    if not isinstance(env_tables, dict):
        raise SafenavError(f"{source}: [envs] must be a table of env ids")
    for env, tables in env_tables.items():
        if not isinstance(tables, dict) or set(tables) - set(SECTIONS):
            raise SafenavError(f"{source}: [envs.{env!r}] may hold only {', '.join(SECTIONS)}")
        envs[env] = _merge(envs.get(env, {}), tables)
    unknown = sorted(set(data) - set(SECTIONS))
    if unknown:
        raise SafenavError(
            f"{source}: unknown section(s) {unknown}; a recipe has {', '.join(SECTIONS)}, envs"
        )
    for k, v in data.items():
        if not isinstance(v, dict):
            raise SafenavError(f"{source}: [{k}] must be a table")
        sections[k] = _merge(sections.get(k, {}), v)
    return Recipe(name=name, algo=str(meta["algo"]), sections=sections, header=header,
                  source=source, algos=tuple(str(a) for a in algos), envs=envs)  # fmt: skip


def apply(obj: Any, overrides: dict[str, Any], where: str = "") -> Any:
    """A copy of the (frozen, nested) dataclass ``obj`` with ``overrides`` set, validated by
    the dataclasses themselves; ``SafenavError`` naming an unknown or invalid field."""
    import dataclasses

    from safenav.common.config import from_dict, to_dict

    names = {f.name for f in dataclasses.fields(obj)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise SafenavError(f"recipe: unknown field(s) {[f'{where}{u}' for u in unknown]}")
    data = to_dict(obj)
    for k, v in overrides.items():
        current = getattr(obj, k)
        if dataclasses.is_dataclass(current) and isinstance(v, dict):
            data[k] = to_dict(apply(current, v, f"{where}{k}."))
        else:
            data[k] = v
    try:
        return from_dict(type(obj), data)
    except (TypeError, ValueError) as err:
        raise SafenavError(
            f"recipe: invalid value in [{where.rstrip('.') or 'section'}]: {err}"
        ) from None


__all__ = ["PPO_ALGOS", "SECTIONS", "Recipe", "apply", "available", "default_recipe",
           "load_recipe", "task_family"]  # fmt: skip
