"""Your copy of the supervisor's restart intensity (`rr-actors teach check` runs it in
place of the supervisor's own, in every supervisor of the simulated run).

A supervisor restarts a child that crashed, but only so often: when more than
`max_restarts` restarts fall within `period` seconds, it gives up (it stops every child
and reports it: OTP's restart intensity). At each crash it would restart, it asks this
step how many restarts count, and gives up if that is more than `max_restarts`.
"""

from collections.abc import Sequence


def recent(times: Sequence[float], now: float, period: float) -> int:
    """How many restarts count toward the restart intensity now.

    Args:
        times: the time of every restart since the supervisor started (seconds, on a
            monotonic clock, the oldest first; this one, at `now`, last).
        now: the time of this restart.
        period: the supervisor's period (seconds).

    Returns:
        The number of restarts that count (this one included).
    """
    # Every restart counts: a child that crashed that often is not to be trusted.
    return len(times)
