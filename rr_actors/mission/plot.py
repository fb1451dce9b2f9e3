"""The mission's figure: distance over time with the faults marked (thesis figure 6.5).

Needs matplotlib (`pip install 'rr-actors[demo]'`); importing this module without it
raises `ImportError`, which `run_mission` takes as "no plot".
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib as mpl

mpl.use("Agg")  # no display needed
import matplotlib.pyplot as plt

if TYPE_CHECKING:
    from rr_actors.mission.report import MissionReport

__all__ = ["plot"]


def plot(report: MissionReport, path: Path) -> None:
    """Draw distance over time, mark each fault's injection and shade the stops.

    Args:
        report: the mission's report.
        path: the PNG file to write.
    """
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=110)
    try:
        if report.trace:
            ts, xs = zip(*report.trace, strict=True)
            ax.plot(ts, xs, color="tab:blue", linewidth=2, label="distance travelled")
        for start, end in report.stops:
            ax.axvspan(start, end, color="tab:red", alpha=0.15, linewidth=0)
        top = max(report.distance_m, 1e-6)
        for fault in report.faults:
            ax.axvline(fault.injected_at_s, color="tab:gray", linestyle="--", linewidth=1)
            ax.annotate(
                fault.id,
                (fault.injected_at_s, top),
                xytext=(3, -12),
                textcoords="offset points",
                fontsize=10,
                fontweight="bold",
            )
        ax.plot([], [], color="tab:red", alpha=0.3, linewidth=8, label="robot stopped")
        ax.set_xlabel("time since the start of the drive (s)")
        ax.set_ylabel("distance (m)")
        ax.set_title(
            f"rr-actors demo: {report.mission_time_s:.1f} s with {len(report.faults)} fault(s) "
            f"(no stop: {report.nominal_time_s:.1f} s)"
        )
        ax.set_xlim(left=0)
        ax.set_ylim(bottom=0, top=top * 1.08)
        ax.grid(visible=True, alpha=0.3)
        ax.legend(loc="lower right")
        fig.tight_layout()
        fig.savefig(path)
    finally:
        plt.close(fig)
