"""`python -m rr_actors_lab.mission`: the same as `rr-actors demo`."""

import sys

from rr_actors_lab.mission.run import main

sys.exit(main())
