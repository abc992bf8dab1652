"""User-facing errors: the CLI prints them as one line ``safenav: error: ...`` and exits with the
error's :attr:`~SafenavError.exit_code` (README, "Exit codes")."""

EXIT_RUNTIME = 1
"""The command line was fine but the work failed: a port in use, too little memory, no permission
to write, no CUDA, a failed trial."""
EXIT_USAGE = 2
"""The command line is wrong: unknown verb or option, malformed or out-of-range value, missing
input file, a directory where a file belongs, an occupied run directory."""


class SafenavError(Exception):
    """A mistake the user can fix in the command line (bad value, missing or unusable file, ...).
    Message names problem and fix. Exit code 2 (a usage error)."""

    exit_code = EXIT_USAGE


class SafenavRuntimeError(SafenavError):
    """The command line is valid but this machine cannot carry it out now (port in use, not
    enough memory, permission denied, device missing). Exit code 1."""

    exit_code = EXIT_RUNTIME


def one_line(text: object, limit: int | None = None) -> str:
    """``text`` with its whitespace runs (newlines, tabs) collapsed to single spaces, cut to
    ``limit`` characters: library messages such as ``load_state_dict``'s span many lines."""
    line = " ".join(str(text).split())
    return line if limit is None or len(line) <= limit else line[: limit - 3].rstrip() + "..."


__all__ = ["EXIT_RUNTIME", "EXIT_USAGE", "SafenavError", "SafenavRuntimeError", "one_line"]
