"""``python -m hybridctl.cli``."""

import sys

from . import main

sys.exit(main())
