"""``safenav <verb>``: the one command-line entry point.

Each verb is a function whose typed signature and docstring tyro turns into ``--help``. Bodies
import lazily so that ``safenav --help`` stays fast. A :class:`~safenav.errors.SafenavError`
(or a ``ValueError`` from config validation) becomes one line on stderr and exit code 2.
"""

from __future__ import annotations

import sys
from typing import Annotated

import tyro

from safenav.errors import SafenavError

app = tyro.extras.SubcommandApp()


def main(argv: list[str] | None = None) -> None:
    """Run the CLI; user mistakes print one line and exit 2, never a traceback."""
    from safenav import commands  # noqa: F401  (registers the verbs on ``app``)

    try:
        app.cli(args=argv, prog="safenav", description="Safe UAV navigation with constrained RL.")
    except (SafenavError, ValueError, FileNotFoundError, PermissionError) as err:
        print(f"safenav: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        print("safenav: interrupted", file=sys.stderr)
        raise SystemExit(130) from None


__all__ = ["Annotated", "app", "main"]
