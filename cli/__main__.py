"""``python -m slipmap.cli``."""

import sys

from . import main

sys.exit(main())
