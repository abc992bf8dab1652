"""User-facing errors: the CLI prints them as one line and exits with code 2."""


class SafenavError(Exception):
    """A mistake the user can fix (bad config, missing file, ...). Message names problem and fix."""
