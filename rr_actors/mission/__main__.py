"""`python -m rr_actors.mission`: the same as `rr-actors demo`."""

import sys

from rr_actors.mission.run import main

sys.exit(main())
