"""User-facing errors: the CLI prints them as one line and exits with code 2."""


class SafenavError(Exception):
    """A mistake the user can fix (bad config, missing file, ...). Message names problem and fix."""


def one_line(text: object, limit: int | None = None) -> str:
    """``text`` with its whitespace runs (newlines, tabs) collapsed to single spaces, cut to
    ``limit`` characters: library messages such as ``load_state_dict``'s span many lines."""
    line = " ".join(str(text).split())
    return line if limit is None or len(line) <= limit else line[: limit - 3].rstrip() + "..."


__all__ = ["SafenavError", "one_line"]
