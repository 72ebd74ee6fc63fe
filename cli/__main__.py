"""``python -m slipmap.cli``."""

from . import entry

entry()
