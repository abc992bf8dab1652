"""The CLI verbs, one module each; importing this package registers them on ``safenav.cli.app``."""

from safenav.commands import (  # noqa: F401
    average,
    bench,
    convert,
    eval,
    export,
    fly,
    plot,
    render,
    reproduce,
    sim_vehicle,
    train,
    tune,
)
