"""``python -m cutterpose.cli``."""

from . import main

main()
