"""``safenav <verb>``: the one command-line entry point.

Each verb is a function whose typed signature and docstring tyro turns into ``--help``. Bodies
import lazily so that ``safenav --help`` stays fast. Every failure is one line
``safenav: error: ...`` on stderr and an exit code (README, "Exit codes"): 2 for a usage error
(tyro's parse errors, :class:`~safenav.errors.SafenavError`, ``ValueError`` from config
validation, a missing input file), 1 for a runtime error
(:class:`~safenav.errors.SafenavRuntimeError`, ``OSError`` such as a port in use or no permission,
out of memory), 130/143 for Ctrl-C/SIGTERM.
"""

from __future__ import annotations

import contextlib
import contextvars
import difflib
import os
import re
import shlex
import sys
from typing import Annotated

import tyro

from safenav.errors import EXIT_RUNTIME, EXIT_USAGE, SafenavError, one_line

app = tyro.extras.SubcommandApp()
ARGS: contextvars.ContextVar[tuple[str, ...]] = contextvars.ContextVar("safenav_args", default=())
"""The command line being run: which options were given, even when given their default value
(``train --resume RUN --device cpu`` of a run trained on cuda)."""

# The verbs in the order ``safenav --help`` lists them, with their one-line summaries (the detail
# is each verb's own --help).
VERBS = {
    "train": "train CSAC, SAC, PPO, PPO-Lag or SAC-Lag into a run directory",
    "eval": "fly a policy on the fixed test scenario: success / collision / timeout",
    "render": "fly one test episode and write a GIF",
    "reproduce": "every algorithm x seed trained and evaluated on Ray; results table",
    "tune": "a recipe's hyperparameters searched on validation maps only",
    "plot": "learning curves and test results of runs as PNG",
    "average": "weight average of a run's kept policies into one policy",
    "export": "a checkpoint's policy as ONNX (or as a small policy-only file)",
    "convert": "an older safenav's checkpoint rewritten to load without pickle",
    "sim-vehicle": "a simulated PX4 vehicle speaking MAVLink on loopback",
    "fly": "fly an ONNX policy on PX4 (or --demo against sim-vehicle)",
    "bench": "throughput, latency and memory benchmarks",
}
EXIT_CODES = ("0 success, 1 runtime error (port in use, no memory or permission), 2 usage error "
              "(bad option, value or path), 3 flight aborted, 4 flight collided, 130 Ctrl-C, "
              "143 SIGTERM")  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    """Run the CLI; every failure prints one line and exits non-zero, never a traceback."""
    args = list(sys.argv[1:] if argv is None else argv)
    if argv is None and args[:1] == ["fly"]:
        # A flight's process ends the moment the flight does: tearing down an interpreter that
        # holds torch, ONNX Runtime and MAVSDK takes 0.5-1 s more on 2 loaded cores, and whoever
        # supervises the companion computer waits for this exit status after a link loss.
        # Everything fly writes (JSON, MCAP, logs) is closed before it returns or raises.
        try:
            _main(args)
            code = 0
        except SystemExit as err:
            code = exit_status(err.code)
        exit_now(code)
    _main(args)


def exit_status(code: object) -> int:
    """The status :class:`SystemExit` carries, as the interpreter would report it (a message is
    printed and counts as 1)."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def exit_now(code: int) -> None:
    """Flush every stream and log handler, then end the process without the interpreter's
    teardown (which only frees memory the OS reclaims anyway)."""
    import logging

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def _main(args: list[str]) -> None:
    if args in (["-h"], ["--help"], ["--version"], ["-V"]):
        try:
            print(short_help() if args[0].startswith("-h") or args[0] == "--help" else version())
        except BrokenPipeError:  # `safenav --help | head -3`
            _quiet_stdout()
        return
    if not args:
        _fail("no verb given: safenav VERB [options]; safenav --help lists the verbs", EXIT_USAGE)
    if args[0] == "help" and len(args) <= 2:  # `safenav help [VERB]`, as git and pip take it
        main(["--help"] if len(args) == 1 else [args[1], "--help"])
        return
    if not args[0].startswith("-") and args[0] not in VERBS:
        close = difflib.get_close_matches(args[0], list(VERBS), n=1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        _fail(f"unknown verb {args[0]!r}: {hint}safenav --help lists the verbs", EXIT_USAGE)
    token = ARGS.set(tuple(args))
    try:
        _run(args)
    except KeyboardInterrupt as err:
        from safenav.common.stopping import Terminated

        terminated = isinstance(err, Terminated)
        print(
            f"safenav: {'terminated (SIGTERM)' if terminated else 'interrupted'}", file=sys.stderr
        )
        raise SystemExit(143 if terminated else 130) from None
    except SystemExit:
        raise
    except BrokenPipeError:  # `safenav ... | head`: the reader left; nothing to report
        _quiet_stdout()
        raise SystemExit(EXIT_RUNTIME) from None
    except BaseException as err:  # noqa: BLE001 -- one line instead of a traceback
        message, code = describe(err)
        if code is None:  # a bug: say so, and how to see it in full
            if os.environ.get("SAFENAV_TRACEBACK"):
                raise
            print(f"safenav: error: {message}", file=sys.stderr)
            _fail("this is a bug in safenav: please report it (SAFENAV_TRACEBACK=1 shows where)",
                  EXIT_RUNTIME)  # fmt: skip
        _fail(message, code)
    finally:
        ARGS.reset(token)


def version() -> str:
    from safenav import __version__

    return f"safenav {__version__}"


def _quiet_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's final flush into a closed pipe stays
    silent."""
    with contextlib.suppress(OSError, ValueError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


_LIST_ITEM = re.compile(r"(\s|[-*•] |\d+[.)] )")


def unwrap_help(text: str) -> str:
    """A docstring as ``--help`` prints it: its wrapped lines joined into paragraphs. tyro's own
    rule (``tyro._strings.remove_single_line_breaks``) also starts a new line wherever a wrapped
    line begins with something other than a letter (a number, ``code``, a --flag, a quote), which
    cut sentences and examples in two; here only blank lines, list items and indented lines
    do. Attribute docstrings arrive with their continuation lines indented: dedented first."""
    import inspect

    parts: list[str] = []
    for line in inspect.cleandoc(text).split("\n"):
        line = line.rstrip()
        if not line:
            if not parts or parts[-1] != "\n":
                parts.append("\n")
            parts.append("\n")
            continue
        if parts and parts[-1] != "\n":
            parts.append("\n" if _LIST_ITEM.match(line) else " ")
        parts.append(line)
    return "".join(parts).rstrip()


def _use_unwrap_help() -> None:
    """Install :func:`unwrap_help` in tyro (a private function of it, looked up by module
    attribute at each use; with a tyro that lacks it, tyro's own rule stays)."""
    strings = getattr(tyro, "_strings", None)
    if strings is not None and hasattr(strings, "remove_single_line_breaks"):
        strings.remove_single_line_breaks = unwrap_help


_use_unwrap_help()  # at import: tyro caches help texts, and parse_train_args uses tyro too


def _run(args: list[str]) -> None:
    from safenav import commands  # noqa: F401  (registers the verbs on ``app``)
    from safenav.common.checks import registry

    with _parse_errors_as_safenav_errors(args[0] if args[0] in VERBS else None):
        app.cli(args=args, prog="safenav", description="Safe UAV navigation with constrained RL.",
                registry=registry())  # fmt: skip


def _fail(message: str, code: int) -> None:
    print(f"safenav: error: {one_line(message)}", file=sys.stderr)
    raise SystemExit(code)


def describe(err: BaseException) -> tuple[str, int | None]:
    """The one-line message and exit code of an exception, or ``(message, None)`` for a bug."""
    import errno

    if isinstance(err, SafenavError):
        return str(err), err.exit_code
    if isinstance(err, ValueError):  # config validation (__post_init__)
        return str(err), EXIT_USAGE
    if isinstance(err, (FileNotFoundError, IsADirectoryError, NotADirectoryError)):
        return _os_message(err), EXIT_USAGE
    if isinstance(err, MemoryError) or type(err).__name__ == "OutOfMemoryError":
        return f"out of memory ({one_line(err, 200) or type(err).__name__})", EXIT_RUNTIME
    if isinstance(err, OSError):
        if err.errno == errno.EADDRINUSE:
            return f"address already in use ({_os_message(err)})", EXIT_RUNTIME
        return _os_message(err), EXIT_RUNTIME
    return f"{type(err).__name__}: {one_line(err, 300)}", None


def _os_message(err: OSError) -> str:
    where = f": {err.filename}" if getattr(err, "filename", None) else ""
    return f"{err.strerror or err}{where}"


def short_help() -> str:
    """``safenav --help``: one screen, the verbs with one line each."""
    from safenav import __version__

    width = max(map(len, VERBS))
    lines = [
        "usage: safenav [-h] [--version] VERB [options]",
        "",
        f"Safe UAV navigation with constrained RL (safenav {__version__}).",
        "",
        "verbs:",
        *(f"  {verb:<{width}}  {text}" for verb, text in VERBS.items()),
        "",
        "options:",
        f"  {'-h, --help':<{width}}  show this help and exit",
        f"  {'--version':<{width}}  show the version and exit",
        "",
        "safenav VERB --help documents every option of VERB.",
        "Exit codes: " + EXIT_CODES + ".",
    ]
    return "\n".join(lines)


def _parse_errors_as_safenav_errors(verb: str | None = None) -> contextlib.AbstractContextManager:
    """Make every tyro parse error (unknown option, missing or malformed value, bad choice, a
    nested config's ``ValueError``) a one-line :class:`SafenavError`, not a boxed message. Uses
    tyro's parse-error hook, which tyro marks private; with a tyro that lacks it the boxed
    message (also exit code 2) remains."""
    on_parse_error = getattr(getattr(tyro, "_errors", None), "on_parse_error", None)
    if on_parse_error is None:
        return contextlib.nullcontext()

    def hook(event: object) -> None:
        raise SafenavError(parse_error_message(event, verb))

    return on_parse_error(hook)


def _flag(argument: object) -> str:
    lowered = getattr(argument, "lowered", None)
    names = getattr(lowered, "name_or_flags", None) or ()
    if names and not str(names[0]).startswith("-"):  # a positional, named by tyro's inner path
        return str(names[0]).rsplit(".", 1)[-1].upper()
    if names:
        return "/".join(names)
    metavar = getattr(lowered, "metavar", None)
    return str(metavar) if metavar else "argument"


def _help_of(prog: str) -> str:
    return f"see {prog} --help"


def verb_flags(verb: str) -> list[str]:
    """The ``--options`` of ``verb``, from its signature as tyro names them (for "did you mean");
    [] if it cannot be told."""
    import dataclasses
    import inspect
    import typing

    spec = getattr(app, "_subcommands", {}).get(verb)  # tyro's registry (private): best effort
    target = getattr(spec, "target", None)
    if target is None:
        return []

    def walk(hints: dict, names: list[str], prefix: str) -> list[str]:
        flags = []
        for name in names:
            tp, arg_name = hints.get(name), None
            if typing.get_origin(tp) is typing.Annotated:
                tp, *extra = typing.get_args(tp)
                if any("Positional" in repr(e) for e in extra):
                    continue  # no --flag
                arg_name = next(
                    (getattr(e, "name", None) for e in extra if hasattr(e, "name")), None
                )
            if dataclasses.is_dataclass(tp):
                sub = prefix if arg_name == "" else f"{prefix}{arg_name or name}."
                fields = [f.name for f in dataclasses.fields(tp)]
                flags += walk(typing.get_type_hints(tp, include_extras=True), fields, sub)
            else:
                flags.append(f"--{prefix}{(arg_name or name).replace('_', '-')}")
        return flags

    try:
        hints = typing.get_type_hints(target, include_extras=True)
        return walk(hints, list(inspect.signature(target).parameters), "")
    except Exception:  # noqa: BLE001 -- a hint, never a new error
        return []


def _switch_given_a_value(tokens: list[str], args: tuple[str, ...]) -> tuple[str, str] | None:
    """``(--switch, value)`` when a left-over token is the value given to an option that takes
    none (``--overwrite=yes``, ``--no-progress yes``): tyro reports only the value, unnamed."""
    for token in tokens:
        if token.startswith("-"):
            continue
        for arg in args:
            name, eq, value = arg.partition("=")
            if eq and name.startswith("--") and value == token:
                return name, token
        # the last occurrence: ``--seed 1 --overwrite 1`` leaves the second 1
        for i in reversed(range(1, len(args))):
            if args[i] == token and args[i - 1].startswith("--") and "=" not in args[i - 1]:
                return args[i - 1], token
    return None


def parse_error_message(event: object, verb: str | None = None) -> str:
    """One line for a tyro ``ParseErrorEvent`` (matched by class name: the module is private)."""
    kind = type(event).__name__
    prog = f"safenav {verb}" if verb else str(getattr(event, "prog", "safenav"))
    if kind == "InstantiationFailure":
        message = re.sub(r"\[/?bold\]", "", str(getattr(event, "message", event)))
        if "Got errors:" in message:  # an optional value ({None}|X): keep X's complaint
            reasons = [r.strip() for r in message.split("Got errors:", 1)[1].split("\n- ")]
            reasons = [re.sub(r"^(<class '[^']*'>|[\w.]+\[.*?\]): ", "", r) for r in reasons
                       if r and "NoneType" not in r]  # fmt: skip
            message = "; ".join(reasons) or message
        flag = _flag(getattr(event, "argument", None))
        nonfinite = re.fullmatch(r"expected a finite number, got '(.*)'", message)
        if nonfinite:  # in the configs' own words: "lr=nan must be ..."
            field = flag.split("/")[0].split(".")[-1].lstrip("-")
            return f"invalid {flag} value: {field}={nonfinite.group(1)} must be a finite number"
        return f"invalid {flag} value: {message}"
    if kind == "UnrecognizedArgs":
        tokens = [str(t) for t in getattr(event, "tokens", [])]
        flag = next((t.split("=")[0] for t in tokens if t.startswith("--")), None)
        switch = None if flag else _switch_given_a_value(tokens, ARGS.get())
        if switch:
            return f"{switch[0]} takes no value ({switch[1]!r}): {_help_of(prog)}"
        close = difflib.get_close_matches(flag, verb_flags(verb), n=1) if flag and verb else []
        hint = f"did you mean {close[0]}? " if close else ""
        return f"unrecognized option(s) {' '.join(tokens)}: {hint}{_help_of(prog)}"
    if kind == "MissingArgs":
        names = []
        for missing in getattr(event, "missing_arguments", []):
            arg = getattr(missing, "arg", missing)
            name, metavar = _flag(arg), str(getattr(getattr(arg, "lowered", None), "metavar", ""))
            choices = metavar.strip("{}").replace(",", ", ") if metavar.startswith("{") else ""
            names.append(f"{name} (one of {choices})" if choices and not name.startswith("-")
                         else name)  # fmt: skip
        return f"missing {', '.join(names)}: {_help_of(prog)}"
    if kind == "BadValue":
        flag = _flag(getattr(event, "argument", None))
        nargs = getattr(getattr(getattr(event, "argument", None), "lowered", None), "nargs", 1)
        if getattr(event, "reason", "") == "too_few_values":
            given = list(ARGS.get())
            after = given[given.index(flag) + 1] if flag in given[:-1] else ""
            hint = (f" (a value that starts with '-' is taken for an option: write "
                    f"{shlex.quote(f'{flag}={after}')})" if after.startswith("-") and nargs == 1
                    else "")  # fmt: skip
            return f"{flag} needs {nargs} value{'s' if nargs != 1 else ''}{hint}: {_help_of(prog)}"
        return (
            f"{flag} takes no value ({getattr(event, 'offending_value', '')!r}): {_help_of(prog)}"
        )
    if kind == "InvalidChoice":
        flag = _flag(getattr(event, "argument", None))
        choices = ", ".join(map(str, getattr(event, "choices", ())))
        return f"{flag} {getattr(event, 'value', '')!r}: choose one of {choices}"
    if kind == "MissingSubcommand":
        return f"no verb given: safenav VERB [options]; {_help_of(prog)}"
    if kind == "MutexConflict":
        first, second = getattr(event, "first_token", "?"), getattr(event, "second_token", "?")
        return f"{first} and {second} cannot be used together: {_help_of(prog)}"
    return f"invalid command line ({kind}): {_help_of(prog)}"


__all__ = ["Annotated", "VERBS", "app", "describe", "main", "parse_error_message", "short_help"]
