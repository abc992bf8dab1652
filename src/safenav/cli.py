"""``safenav <verb>``: the one command-line entry point.

Each verb is a function whose typed signature and docstring tyro turns into ``--help``. Bodies
import lazily so that ``safenav --help`` stays fast. A :class:`~safenav.errors.SafenavError`
(or a ``ValueError`` from config validation) becomes one line on stderr and exit code 2.
"""

from __future__ import annotations

import contextlib
import sys
from typing import Annotated

import tyro

from safenav.errors import SafenavError, one_line

app = tyro.extras.SubcommandApp()


def main(argv: list[str] | None = None) -> None:
    """Run the CLI; user mistakes print one line and exit 2, never a traceback."""
    from safenav import commands  # noqa: F401  (registers the verbs on ``app``)

    try:
        with _value_errors_as_safenav_errors():
            app.cli(
                args=argv, prog="safenav", description="Safe UAV navigation with constrained RL."
            )
    except (SafenavError, ValueError, FileNotFoundError, PermissionError) as err:
        # one line even when the message quotes a multi-line library error
        print(f"safenav: error: {one_line(err)}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt as err:
        from safenav.common.stopping import Terminated

        terminated = isinstance(err, Terminated)
        print(
            f"safenav: {'terminated (SIGTERM)' if terminated else 'interrupted'}", file=sys.stderr
        )
        raise SystemExit(143 if terminated else 130) from None


def _value_errors_as_safenav_errors() -> contextlib.AbstractContextManager:
    """Make a bad option value (``--csac.actor-lr -1``, ``--num-envs abc``) a one-line
    :class:`SafenavError` too: tyro catches the ``ValueError`` of a nested config's validation
    and would print a boxed usage message instead. Uses tyro's parse-error hook, which tyro
    marks private; with a tyro that lacks it the boxed message (also exit code 2) remains."""
    on_parse_error = getattr(getattr(tyro, "_errors", None), "on_parse_error", None)
    if on_parse_error is None:
        return contextlib.nullcontext()

    def hook(event: object) -> None:
        if type(event).__name__ != "InstantiationFailure":
            return  # tyro's own message: unknown flags with suggestions, missing values, ...
        lowered = getattr(getattr(event, "argument", None), "lowered", None)
        flag = "/".join(getattr(lowered, "name_or_flags", None) or ())
        raise SafenavError(f"invalid {flag or 'option'} value: {getattr(event, 'message', event)}")

    return on_parse_error(hook)


__all__ = ["Annotated", "app", "main"]
