import sys

from flocktrack.cli import main

sys.exit(main())
