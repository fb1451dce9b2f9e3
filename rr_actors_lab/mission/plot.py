"""The mission's figure: this run beside the thesis's (figure 6.5), and a zoom on one stop.

    ┌ distance over the mission clock ───────────────┐ ┌ zoom on the longest stop ─┐
    │ this run (blue), its faults F1-F6 (dotted)     │ │ odometry samples, the     │
    │ the thesis's run (orange), its 3 s and 5 s     │ │ stop shaded, when FATAL   │
    │ stops shaded; a box where the zoom looks       │ │ was heard and recovered   │
    └────────────────────────────────────────────────┘ └───────────────────────────┘

Across two hosts each fault's marker names where it struck (`F4 station`), and F6's cut
is hatched. The thesis's run is redrawn from section 6.2's figures (43 s with faults,
stopped 3 s at F1 and 5 s at F2) over this run's path, so it is labelled as redrawn.

Needs matplotlib (`pip install 'rr-actors[demo]'`); importing this module without it
raises `ImportError`, which `run_mission` takes as "no plot".
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib as mpl

mpl.use("Agg")  # no display needed
import itertools

import matplotlib.pyplot as plt
from matplotlib.patches import ConnectionPatch, Rectangle

from rr_actors_lab.mission.config import DEFAULT_FAULT_AT
from rr_actors_lab.mission.report import SHORT_WHAT, THESIS

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from rr_actors_lab.mission.report import FaultResult, MissionReport

__all__ = ["plot", "thesis_trace"]

OURS = "tab:blue"
THEIRS = "tab:orange"
STOPPED = "tab:red"


def thesis_trace(distance_m: float, start_s: float = 0.0) -> list[tuple[float, float]]:
    """The thesis's run (section 6.2, figure 6.5) as the `(t, x)` corners of a piecewise-linear
    curve over `distance_m` from `start_s`: the speed that makes 43 s, and its stops (3 s at
    F1, 5 s at F2) where the demo injects those faults by default."""
    total = THESIS["mission_time_s"]["with_faults"]
    stops = {
        f: seconds for f, seconds in THESIS["robot_stopped_s"].items() if seconds > 0
    }  # F1, F2
    speed = distance_m / (total - sum(stops.values()))
    t, x = start_s, 0.0
    corners = [(t, x)]
    for fault in sorted(stops, key=lambda f: DEFAULT_FAULT_AT[f]):
        at = DEFAULT_FAULT_AT[fault] * distance_m
        t += (at - x) / speed
        x = at
        corners.append((t, x))
        t += stops[fault]
        corners.append((t, x))
    t += (distance_m - x) / speed
    corners.append((t, distance_m))
    return corners


def _label(fault: FaultResult) -> str:
    """A fault's marker: its id, and across two hosts where it struck (`F4 station`)."""
    return f"{fault.id} {fault.host}" if fault.host else fault.id


def _thesis_stop(fault: FaultResult) -> str:
    """How long the thesis's robot stopped at `fault` (`thesis: 3 s`), or that the thesis
    had no such fault (`thesis: no WiFi cut`: F6 is ours, its section 6.2 has F1-F5)."""
    stopped = THESIS["robot_stopped_s"].get(fault.id)
    if stopped is None:
        return f"thesis: no {SHORT_WHAT.get(fault.id, fault.what)}"
    return f"thesis: {stopped:g} s"


def _zoomed(report: MissionReport) -> tuple[FaultResult, float, float] | None:
    """The fault whose stop the zoom shows (the longest), and the zoom's time window."""
    if not report.faults:
        return None
    fault = max(report.faults, key=lambda f: f.robot_stopped_s)
    begin = fault.injected_at_s
    end = begin + max(
        fault.robot_stopped_s,
        fault.recovered_after_s or 0.0,
        fault.detected_after_s or 0.0,
        0.05,
    )
    margin = max(0.15, 0.6 * (end - begin))
    return fault, begin - margin, end + margin


def _main_panel(ax: Axes, report: MissionReport) -> None:
    top = max(report.distance_m, 1e-6)
    theirs = thesis_trace(top, report.drive_started_s)
    end = max(theirs[-1][0], *(t for t, _ in report.trace))
    if report.drive_started_s > 0:
        ax.axvspan(0, report.drive_started_s, color="0.5", alpha=0.1, linewidth=0)
    if report.drive_started_s > 0.08 * end:  # room for its label
        ax.annotate(
            "managers start,\nrobot and LiDAR load",
            (report.drive_started_s / 2, top * 0.5),
            ha="center",
            fontsize=8,
            color="0.35",
            rotation=90,
            va="center",
        )
    ts, xs = zip(*theirs, strict=True)
    ax.plot(
        ts, xs, color=THEIRS, linewidth=2, linestyle="--", label="TeMoto thesis, fig. 6.5 (redrawn)"
    )
    for (t0, x0), (t1, x1) in itertools.pairwise(theirs):
        if x0 == x1:  # a stop of the thesis's run
            ax.axvspan(t0, t1, color=THEIRS, alpha=0.15, linewidth=0)
            ax.annotate(
                f"thesis: stopped {t1 - t0:.0f} s",
                ((t0 + t1) / 2, x0),
                xytext=(0, -22),
                textcoords="offset points",
                ha="center",
                fontsize=8,
                color="tab:brown",
            )
    if report.trace:
        ts, xs = zip(*report.trace, strict=True)
        ax.plot(ts, xs, color=OURS, linewidth=2, label="rr-actors demo (this run)")
    for start, stop in report.stops:
        ax.axvspan(start, stop, color=STOPPED, alpha=0.25, linewidth=0)
    cuts = [f for f in report.faults if f.details.get("link_up_after_s") is not None]
    for fault in cuts:  # F6: the link between the hosts was down
        ax.axvspan(
            fault.injected_at_s,
            fault.injected_at_s + fault.details["link_up_after_s"],
            facecolor="none",
            edgecolor="0.6",
            hatch="//",
            linewidth=0,
        )
    for i, fault in enumerate(report.faults):
        ax.axvline(fault.injected_at_s, color="tab:gray", linestyle=":", linewidth=1)
        ax.annotate(
            _label(fault),
            (fault.injected_at_s, top * (1.1 if i % 2 == 0 else 1.04)),  # close ones: apart
            xytext=(2, -2),
            textcoords="offset points",
            fontsize=9,
            fontweight="bold",
            va="top",
        )
    for pause in report.pauses_s:
        ax.plot([pause], [0], marker="^", color="tab:purple", markersize=6, clip_on=False)
    if report.pauses_s:
        ax.plot(
            [],
            [],
            marker="^",
            color="tab:purple",
            linestyle="",
            label="paused for Enter (not counted)",
        )
    ax.plot([], [], color=STOPPED, alpha=0.4, linewidth=8, label="this run's robot stopped")
    if cuts:
        ax.fill_between(
            [],
            [],
            facecolor="none",
            edgecolor="0.6",
            hatch="//",
            linewidth=0,
            label="link between the hosts down",
        )
    ax.plot([], [], color=THEIRS, alpha=0.3, linewidth=8, label="the thesis's robot stopped")
    ax.set_xlabel("mission clock (s): the story's and the timeline's")
    ax.set_ylabel("distance (m)")
    ax.set_xlim(left=0, right=end * 1.02)
    ax.set_ylim(bottom=0, top=top * 1.12)
    ax.grid(visible=True, alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)


def _zoom_panel(ax: Axes, main: Axes, report: MissionReport) -> None:
    zoom = _zoomed(report)
    assert zoom is not None
    fault, left, right = zoom
    inside = [(t, x) for t, x in report.trace if left <= t <= right]
    if inside:
        ts, xs = zip(*inside, strict=True)
        ax.plot(ts, xs, color=OURS, linewidth=1.5, marker=".", markersize=4)
    for start, end in report.stops:
        if end >= left and start <= right:
            ax.axvspan(start, end, color=STOPPED, alpha=0.25, linewidth=0)
    marks = [("injected", fault.injected_at_s, "tab:gray")]
    if fault.detected_after_s is not None:
        marks.append(("FATAL heard", fault.injected_at_s + fault.detected_after_s, "tab:red"))
    if fault.recovered_after_s is not None:
        marks.append(("recovered", fault.injected_at_s + fault.recovered_after_s, "tab:green"))
    low, high = (min(xs), max(xs)) if inside else (0.0, report.distance_m)
    span = max(high - low, 0.05)
    for i, (label, t, color) in enumerate(marks):
        ax.axvline(t, color=color, linestyle="--", linewidth=1)
        ax.annotate(
            f"{label}\n{(t - fault.injected_at_s) * 1000:+.0f} ms",
            (t, high + span * (0.05 + 0.16 * (len(marks) - 1 - i))),
            xytext=(3, 0),
            textcoords="offset points",
            fontsize=8,
            color=color,
            va="bottom",
            bbox={"facecolor": "white", "alpha": 0.85, "edgecolor": "none", "pad": 1},
        )
    ax.set_title(
        f"{_label(fault)} up close: stopped {fault.robot_stopped_s * 1000:.0f} ms\n"
        f"({_thesis_stop(fault)})",  # (two lines: the panel is narrow)
        fontsize=10,
    )
    ax.set_xlim(left, right)
    ax.set_ylim(low - span * 0.1, high + span * 0.6)
    ax.set_xlabel("mission clock (s)")
    ax.set_ylabel("distance (m)")
    ax.grid(visible=True, alpha=0.3)
    y0, y1 = ax.get_ylim()
    main.add_patch(
        Rectangle((left, y0), right - left, y1 - y0, fill=False, edgecolor="black", linewidth=0.8)
    )
    for y in (y0, y1):
        main.figure.add_artist(
            ConnectionPatch(
                (right, y),
                (left, y),
                "data",
                "data",
                axesA=main,
                axesB=ax,
                color="0.6",
                linewidth=0.6,
            )
        )


def plot(report: MissionReport, path: Path) -> None:
    """Draw this run beside the thesis's and a zoom on its longest stop; write a PNG.

    Args:
        report: the mission's report.
        path: the PNG file to write.
    """
    zoom = bool(report.faults)
    fig, axes = plt.subplots(
        1,
        2 if zoom else 1,
        figsize=(12, 5) if zoom else (9, 5),
        dpi=110,
        gridspec_kw={"width_ratios": [2.3, 1]} if zoom else None,
        squeeze=False,
    )
    try:
        main = axes[0][0]
        _main_panel(main, report)
        if zoom:
            _zoom_panel(axes[0][1], main, report)
        thesis = THESIS["mission_time_s"]
        across = f" on two hosts ({', '.join(report.hosts)})" if report.hosts else ""
        fig.suptitle(
            f"rr-actors demo{across}: {report.mission_time_s:.1f} s of driving with "
            f"{len(report.faults)} fault(s) (no stop: {report.nominal_time_s:.1f} s); "
            f"TeMoto thesis, figure 6.5: {thesis['with_faults']:g} s "
            f"(no stop: {thesis['without_faults']:g} s)",
            fontsize=11,
        )
        fig.tight_layout()
        fig.savefig(path)
    finally:
        plt.close(fig)
