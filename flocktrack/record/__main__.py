"""``python -m flocktrack.record``: the recorder role (:mod:`flocktrack.record.recorder`)."""

import sys

from .recorder import main

sys.exit(main())
