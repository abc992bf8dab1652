"""The CLI verbs, one module each; importing this package registers them on ``safenav.cli.app``."""

from safenav.commands import bench, eval, plot, render, reproduce  # noqa: F401
from safenav.commands import export, fly, sim_vehicle  # noqa: F401
from safenav.commands import train  # noqa: F401
