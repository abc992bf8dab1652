"""``python -m safenav`` = the ``safenav`` command."""

from safenav.cli import main

main()
