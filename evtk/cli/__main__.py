"""``python -m evtk.cli``."""

import sys

from . import main

sys.exit(main())
