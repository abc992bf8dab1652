"""The package's layers: a module imports from its own layer and those below, never from above.

    errors <- common <- envs <- nn <- algos <- training, recipes <- experiments, deploy, bench
           <- commands, cli, demo <- __main__

(``safenav/__init__.py`` registers the envs: it sits with them.) Every ``import`` and ``from ...
import`` of every module under ``src/safenav`` counts, at any depth (a function's lazy import too).
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "safenav"

LAYERS = {
    "errors": 0,
    "common": 1,
    "envs": 2,
    "__init__": 2,
    "nn": 3,
    "algos": 4,
    "training": 5,
    "recipes": 5,
    "experiments": 6,
    "deploy": 6,
    "bench": 6,
    "commands": 7,
    "cli": 7,
    "demo": 7,
    "__main__": 8,
}
"""Top-level package or module of ``safenav`` -> its layer."""


def part(module: str) -> str:
    """``safenav.algos.csac`` -> ``algos``; ``safenav`` -> ``__init__``."""
    names = module.split(".")
    return names[1] if len(names) > 1 else "__init__"


def module_name(path: Path) -> str:
    rel = path.relative_to(SRC.parent).with_suffix("")
    names = list(rel.parts)
    return ".".join(names[:-1] if names[-1] == "__init__" else names)


def is_module(name: str) -> bool:
    """Whether ``safenav.<name>`` is a module or package (else a name in ``safenav/__init__``)."""
    return (SRC / name).is_dir() or (SRC / f"{name}.py").is_file()


def imports(path: Path) -> list[tuple[int, str]]:
    """``(line, imported safenav module)`` of every import in ``path`` (relative ones resolved)."""
    package = module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join([*package[: len(package) - node.level + 1], *filter(None, [base])])
            names = [f"safenav.{a.name}" if is_module(a.name) else base for a in node.names] if base == "safenav" else [base]  # fmt: skip
            out += [(node.lineno, n) for n in names]
    return [(line, m) for line, m in out if m == "safenav" or m.startswith("safenav.")]


def upward_imports() -> list[str]:
    found = []
    for path in sorted(SRC.rglob("*.py")):
        own = part(module_name(path))
        for line, target in sorted(imports(path)):
            if LAYERS[part(target)] > LAYERS[own]:
                found.append(f"{path.relative_to(SRC.parent)}:{line}: {own} (layer {LAYERS[own]}) "
                             f"imports {target} (layer {LAYERS[part(target)]})")  # fmt: skip
    return found


def test_every_part_has_a_layer():
    parts = {part(module_name(p)) for p in SRC.rglob("*.py")}
    assert parts <= set(LAYERS), f"place {sorted(parts - set(LAYERS))} in LAYERS"


def test_no_module_imports_from_a_layer_above_its_own():
    assert upward_imports() == []


def test_the_check_sees_lazy_relative_and_package_imports(tmp_path, monkeypatch):
    """The check itself: an upward import inside a function, a relative one and ``from safenav
    import x`` are all found."""
    pkg = tmp_path / "safenav"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    for sub in ("common", "training", "commands"):
        (pkg / sub).mkdir(exist_ok=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "common" / "a.py").write_text("def f():\n    from safenav.algos import csac\n")
    (pkg / "common" / "b.py").write_text("from ..training import trainer\n")
    (pkg / "common" / "c.py").write_text(
        "from safenav import commands\nimport safenav.errors\nfrom safenav import __version__\n"
    )
    monkeypatch.setitem(globals(), "SRC", pkg)
    found = upward_imports()
    assert [f.split(":")[0] for f in found] == [
        "safenav/common/a.py",
        "safenav/common/b.py",
        "safenav/common/c.py",
        "safenav/common/c.py",
    ]
    assert "imports safenav.training (layer 5)" in found[1]
    assert "imports safenav.commands (layer 7)" in found[2]
    assert found[3].endswith("imports safenav (layer 2)")  # the package root: with the envs
