"""The TeMoto thesis's fault-injected robot mission (chapter 6), on real processes.

A Jackal robot drives to a goal while five faults hit it: its LiDAR is disconnected (F1),
its motor driver fails (F2), and each of its three managers is killed (F3-F5). The
managers run as OS processes under one supervisor; every fault is a real SIGKILL.

    python examples/jackal_mission.py            # the thesis's 16 m at 0.5 m/s (32 s)
    python examples/jackal_mission.py --fast     # a few seconds
    python examples/jackal_mission.py --help

This is the same program as `rr-actors demo`; see docs/tutorial/mission.md.
"""

import sys

from rr_actors_lab.mission import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
