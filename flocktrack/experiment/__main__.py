"""``python -m flocktrack.experiment``: the same as ``flocktrack sweep``."""

import sys

from .sweep import main

sys.exit(main())
