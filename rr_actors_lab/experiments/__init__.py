"""Supervision experiments: a tree, a workload and faults from a TOML plan, run and measured.

```python
from rr_actors_lab import experiments

results = experiments.run(experiments.plans.find("strategies"), out="results", repeat=3)
for row in results.rows():
    print(row["value"], row["recovery_median_s"], row["calls_failed"])
```

`rr-actors experiment PLAN --out DIR` does the same from the command line (PLAN: a file,
or the name of a plan shipped in `plans`: `rr-actors experiment --list`). A plan names
the managers by their `setup`'s import path, the clients' calls, the faults and when they
come (fixed times, seeded random intervals, or after an event). Every run is a fresh run
process; the same seed gives the same fault schedule. The plan format:
`docs/reference/plan.md`; the modules: docs/reference/modules.md. It needs Linux
(pidfds, `/proc`).
"""

from rr_actors._extras import needs

with needs("experiments", "rr_actors_lab.experiments"):  # msgspec: one line if it is missing
    from rr_actors_lab.experiments.experiment import (
        ExperimentError,
        ExperimentInterruptedError,
        Progress,
        run,
    )
    from rr_actors_lab.experiments.plan import FAULT_KINDS, Plan, PlanError
    from rr_actors_lab.experiments.reading import load_plan, parse_plan
    from rr_actors_lab.experiments.results import CallRecord, FaultRecord, Results, RunResult
    from rr_actors_lab.experiments.schedule import ScheduledFault, fault_schedule
    from rr_actors_lab.experiments.workload import RequestContext

__all__ = [
    "FAULT_KINDS",
    "CallRecord",
    "ExperimentError",
    "ExperimentInterruptedError",
    "FaultRecord",
    "Plan",
    "PlanError",
    "Progress",
    "RequestContext",
    "Results",
    "RunResult",
    "ScheduledFault",
    "fault_schedule",
    "load_plan",
    "parse_plan",
    "run",
]
