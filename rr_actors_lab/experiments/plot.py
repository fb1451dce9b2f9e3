"""The experiment's figures: recovery times per compared value, and timelines of runs.

With `[hosts]`, points and lines take the colour of the host a fault hit (`recovery.png`
gets a row for faults between hosts: time to fail and heal; `timeline.png` names each
lane's host and hatches faults between hosts while they last).

Needs matplotlib (`pip install 'rr-actors[experiments]'`); importing this module without
it raises `ImportError`, which `run` takes as "no plots".
"""

from __future__ import annotations

import random
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import matplotlib as mpl

mpl.use("Agg")  # no display needed
import matplotlib.pyplot as plt

from rr_actors_lab.experiments.metrics import affected_hosts
from rr_actors_lab.experiments.plan import HOST_KINDS, Plan
from rr_actors_lab.experiments.results import FaultRecord, Results, RunResult, show_value

__all__ = ["plot_recovery", "plot_timeline"]

_SHORT = {
    "kill_manager": "kill",
    "kill_resource": "kill proc",
    "hang_manager": "hang",
    "load_error": "load err",
    "cut_connections": "cut",
}


HOST_COLOURS = (
    "tab:blue",
    "tab:orange",
    "tab:olive",
    "tab:cyan",
    "tab:brown",
    "tab:pink",
    "tab:purple",
    "tab:gray",
)
"""A colour per host, in the order of `[hosts]` (at most `MAX_HOSTS`, 8); a fault that hit
several hosts (a partition of two) takes the colour of its first."""

KIND_MARKERS = {"cut": "o", "partition": "D", "freeze": "s", "kill_router": "X"}


def _label(results: Results, value: Any) -> str:
    return results.plan.tree.strategy if value is None else show_value(value)


def _fault_host(plan: Plan, fault: FaultRecord) -> str:
    """The host a fault hit, as its points are labelled (`"b"`, `"b+c"`): its manager's, the
    run's own for an untargeted `kill_resource`, for a fault between hosts those it took
    from the clients."""
    assert plan.hosts is not None
    names = plan.hosts.names
    if fault.kind in HOST_KINDS:
        side = plan.faults[fault.fault].hosts if fault.fault < len(plan.faults) else ()
        hit = affected_hosts(fault.kind, fault.target, names, side)
        return "+".join(h for h in names if h in hit) or plan.hosts.home
    try:
        return plan.host_of(fault.target) or plan.hosts.home if fault.target else plan.hosts.home
    except KeyError:  # a target that is not a manager of this variant
        return plan.hosts.home


def _host_colours(plan: Plan) -> dict[str, str]:
    assert plan.hosts is not None
    return dict(zip(plan.hosts.names, HOST_COLOURS, strict=False))


def _colour(colours: dict[str, str], host: str) -> str:
    return colours.get(host.split("+", 1)[0], "black")


def _in_order(hit: Iterable[str], colours: dict[str, str]) -> list[str]:
    """The hosts a legend names, in the order of `[hosts]` (`b+c` after `b`)."""
    names = list(colours)
    return sorted(hit, key=lambda h: (names.index(h.split("+", 1)[0]), h))


def plot_recovery(results: Results, path: Path) -> None:
    """Box plots per compared value: recovery per fault, downtime and failed calls per run.

    Args:
        results: the experiment's results.
        path: the PNG file to write.
    """
    variants = dict(enumerate(p for _, p in results.plan.variants))
    groups = [(value, runs) for value, runs in results.by_value() if runs]
    plans = [variants[i] for i, (_, runs) in enumerate(results.by_value()) if runs]
    labels = [_label(results, value) for value, _ in groups]
    panels = [
        (
            [[r * 1e3 for run in runs for r in run.recoveries()] for _, runs in groups],
            "tab:blue",
            "recovery time (ms)",
            f"recovery per fault, by {results.plan.setting_label() or 'strategy'}",
        ),
        (
            [[sum(run.unavailable_s.values()) for run in runs] for _, runs in groups],
            "tab:purple",
            "seconds (all managers)",
            "not serving, per run",
        ),
        (
            [[float(run.calls_failed) for run in runs] for _, runs in groups],
            "tab:red",
            "calls",
            "failed calls, per run",
        ),
    ]
    hosts = results.plan.hosts is not None
    if hosts:
        fig = plt.figure(figsize=(12, 8.4), dpi=110)
        grid = fig.add_gridspec(2, 14)
        axes = [fig.add_subplot(grid[0, :6]), fig.add_subplot(grid[0, 6:10])]
        axes.append(fig.add_subplot(grid[0, 10:]))
        between = (fig.add_subplot(grid[1, :7]), fig.add_subplot(grid[1, 7:]))
    else:
        fig, axes = plt.subplots(
            1, 3, figsize=(12, 4.2), dpi=110, gridspec_kw={"width_ratios": [3, 2, 2]}
        )
    try:
        jitter = random.Random(0)  # noqa: S311 - where dots go, not a secret
        for number, (ax, (data, colour, ylabel, title)) in enumerate(
            zip(axes, panels, strict=True)
        ):
            ax.boxplot(
                [d if d else [float("nan")] for d in data],
                showfliers=False,
                medianprops={"color": colour, "linewidth": 2},
            )
            ax.set_xticks(range(1, len(labels) + 1), labels)
            if hosts and number == 0:  # each fault's point in its host's colour
                _recovery_by_host(ax, plans, groups, jitter)
            else:
                for index, values in enumerate(data, start=1):
                    xs = [index + jitter.uniform(-0.12, 0.12) for _ in values]
                    ax.scatter(xs, values, s=10, color=colour, alpha=0.5, zorder=3)
            ax.grid(visible=True, axis="y", alpha=0.3)
            ax.set_ylim(bottom=0)
            ax.set_ylabel(ylabel)
            ax.set_title(title, fontsize=10)
        for index, (_, runs) in enumerate(groups, start=1):
            faults = sum(1 for run in runs for f in run.faults if not f.skipped)
            lost = sum(run.unrecovered for run in runs)
            gave_up = sum(1 for run in runs if run.gave_up)
            note = f"{faults} faults" + (f"\n{lost} not recovered" if lost else "")
            note += f"\ngave up in {gave_up} run(s)" if gave_up else ""
            axes[0].annotate(
                note,
                (index, 0),
                xytext=(0, -30),
                textcoords="offset points",
                ha="center",
                va="top",
                fontsize=8,
                annotation_clip=False,
            )
        if hosts:
            _between_hosts(between, plans, groups, labels)
        fig.suptitle(
            f"{results.plan.name}: {len(results.runs)} runs "
            f"({results.plan.repeat} per value, {results.plan.duration:g} s each); "
            f"verdicts: {_verdicts(results)}",
            fontweight="bold",
        )
        fig.tight_layout()
        fig.savefig(path)
    finally:
        plt.close(fig)


def _recovery_by_host(
    ax: Any,
    plans: list[Plan],
    groups: list[tuple[Any, list[RunResult]]],
    jitter: random.Random,
) -> None:
    """Recovery per fault, its points grouped and coloured by the host the fault hit."""
    colours = _host_colours(plans[0])
    hit: dict[str, None] = {}  # the hosts that have points, in order
    for index, (plan, (_, runs)) in enumerate(zip(plans, groups, strict=True), start=1):
        points: dict[str, list[float]] = {}
        for run in runs:
            for fault in run.faults:
                if fault.recovery_s is not None:
                    points.setdefault(_fault_host(plan, fault), []).append(fault.recovery_s * 1e3)
        order = dict.fromkeys(h for h in (*colours, *sorted(points)) if h in points)
        for place, host in enumerate(order):
            centre = index + (place - (len(points) - 1) / 2) * 0.5 / max(len(points), 1)
            xs = [centre + jitter.uniform(-0.05, 0.05) for _ in points[host]]
            ax.scatter(xs, points[host], s=12, color=_colour(colours, host), alpha=0.7, zorder=3)
            hit[host] = None
    for host in _in_order(hit, colours):
        ax.scatter([], [], s=12, color=_colour(colours, host), label=f"host {host}")
    if hit:
        ax.legend(title="fault hit", fontsize=8, title_fontsize=8, loc="best")


def _between_hosts(
    axes: tuple[Any, Any],
    plans: list[Plan],
    groups: list[tuple[Any, list[RunResult]]],
    labels: list[str],
) -> None:
    """The faults between hosts: time to fail and time to heal, per compared value."""
    colours = _host_colours(plans[0])
    kinds: dict[str, None] = {}
    hit: dict[str, None] = {}
    highest = 0.0
    for ax, field, title in (
        (axes[0], "fail_s", "time to fail: from the fault to the first call that failed"),
        (axes[1], "heal_s", "time to heal: from the fault's end to the first call answered"),
    ):
        for index, (plan, (_, runs)) in enumerate(zip(plans, groups, strict=True), start=1):
            faults = [
                (plan, f)
                for run in runs
                for f in run.faults
                if f.kind in HOST_KINDS and f.injected_s is not None and not f.skipped
            ]
            present = sorted({f.kind for _, f in faults}, key=list(KIND_MARKERS).index)
            missing = 0
            for _, fault in faults:
                seconds = getattr(fault, field)
                if seconds is None:
                    missing += 1
                    continue
                place = present.index(fault.kind)
                x = index + (place - (len(present) - 1) / 2) * 0.22
                host = _fault_host(plan, fault)
                ax.scatter(
                    [x],
                    [seconds],
                    marker=KIND_MARKERS.get(fault.kind, "o"),
                    s=30,
                    color=_colour(colours, host),
                    alpha=0.75,
                    zorder=3,
                )
                kinds[fault.kind] = None
                hit[host] = None
                highest = max(highest, seconds)
            if field == "fail_s" and plan.hosts is not None:  # a silent link shows after it
                ax.hlines(plan.hosts.lease, index - 0.4, index + 0.4, color="0.4", linestyle=":")
                highest = max(highest, plan.hosts.lease)
            what = "no call failed" if field == "fail_s" else "not healed in the run"
            ax.annotate(
                f"{len(faults)} faults" + (f"\n{missing}: {what}" if missing else ""),
                (index, 0),
                xytext=(0, -30),
                textcoords="offset points",
                ha="center",
                va="top",
                fontsize=8,
                annotation_clip=False,
            )
        ax.set_xticks(range(1, len(labels) + 1), labels)
        ax.set_xlim(0.5, len(labels) + 0.5)
        ax.grid(visible=True, axis="y", alpha=0.3)
        ax.set_ylabel("seconds")
        ax.set_title(title, fontsize=10)
    for ax in axes:  # the same scale for both, with room for the legend above the points
        ax.set_ylim(0, highest * 1.4 if highest > 0 else 1.0)
    axes[0].plot([], [], color="0.4", linestyle=":", label="lease")
    for kind in kinds:
        axes[0].scatter([], [], marker=KIND_MARKERS.get(kind, "o"), color="0.3", label=kind)
    for host in _in_order(hit, colours):
        axes[0].scatter([], [], marker="o", color=_colour(colours, host), label=f"host {host}")
    if kinds:
        axes[0].legend(fontsize=8, loc="upper left", ncol=1 + len(kinds) + len(hit))


def _verdicts(results: Results) -> str:
    kinds = ("held", "violated", "unverifiable")
    counts = {k: sum(1 for r in results.runs if r.verdict == k) for k in kinds}
    return ", ".join(f"{counts[k]} {k}" for k in kinds)


def _first_runs(results: Results) -> list[tuple[Any, RunResult, Plan]]:
    """The first run of each compared value (at most four), with its value's plan."""
    return [
        (value, runs[0], plan)
        for (value, runs), (_, plan) in zip(results.by_value(), results.plan.variants, strict=True)
        if runs
    ][:4]


def plot_timeline(results: Results, path: Path) -> None:
    """One timeline per compared value (its first run): downtime, restarts, faults, calls.

    Args:
        results: the experiment's results.
        path: the PNG file to write.
    """
    shown = _first_runs(results)
    rows = len(results.plan.managers()) + 1
    fig, axes = plt.subplots(
        len(shown), 1, figsize=(10, 1.5 + 0.42 * rows * len(shown)), dpi=110, squeeze=False
    )
    try:
        for (value, run, plan), ax in zip(shown, axes[:, 0], strict=True):
            _timeline(ax, results, value, run, plan)
        axes[-1, 0].set_xlabel("seconds since the workload started")
        handles, labels = axes[0, 0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8)
        fig.tight_layout(rect=(0, 0.35 / fig.get_figheight(), 1, 1))
        fig.savefig(path)
    finally:
        plt.close(fig)


def _timeline(ax: Any, results: Results, value: Any, run: RunResult, plan: Plan) -> None:
    managers = [m.name for m in plan.managers()]
    colours = _host_colours(plan) if plan.hosts is not None else {}
    end = max(
        [run.duration_s]
        + [c.end_s for c in run.calls]
        + [e for spans in run.down.values() for _, e in spans if e is not None]
    )
    lane = {name: index + 1 for index, name in enumerate(reversed(managers))}
    for name in managers:
        y = lane[name]
        spans = [(s, (e if e is not None else end) - s) for s, e in run.down.get(name, ())]
        ax.broken_barh(spans, (y - 0.3, 0.6), color="tab:red", alpha=0.6, linewidth=0)
        restarts = run.restart_times.get(name, ())
        ax.scatter(restarts, [y] * len(restarts), marker="^", color="tab:green", s=28, zorder=3)
    ok = [c.end_s for c in run.calls if c.ok]
    failed = [c.end_s for c in run.calls if not c.ok]
    ax.scatter(ok, [0] * len(ok), marker="|", color="tab:gray", s=40, linewidths=0.8)
    ax.scatter(failed, [0] * len(failed), marker="x", color="tab:red", s=25, zorder=3)
    labelled = -1.0
    for fault in run.faults:
        if fault.injected_s is None:
            continue
        host = _fault_host(plan, fault) if colours else ""
        colour = _colour(colours, host) if colours else "black"
        ax.axvline(fault.injected_s, color=colour, linestyle="--", linewidth=0.8, alpha=0.7)
        lasted = plan.faults[fault.fault].for_s if fault.fault < len(plan.faults) else None
        if fault.kind in HOST_KINDS and lasted:  # the link down, the router stopped
            ax.axvspan(
                fault.injected_s,
                fault.injected_s + lasted,
                facecolor="none",
                edgecolor=colour,
                hatch="//",
                alpha=0.35,
                linewidth=0,
            )
        if fault.injected_s - labelled < end / 14:
            continue  # no room for another label here
        labelled = fault.injected_s
        text = f"{_SHORT.get(fault.kind, fault.kind)} {fault.target or ''}".strip()
        if host and fault.kind not in HOST_KINDS:  # a cut's or a freeze's names its hosts
            text += f" @{host}"
        ax.annotate(
            text,
            (fault.injected_s, len(managers) + 0.55),
            xytext=(2, 0),
            textcoords="offset points",
            fontsize=7,
            va="bottom",
            color=colour,
        )
    for supervisor, at in run.give_ups:
        ax.annotate(
            f"{supervisor} gave up",
            (at, -0.45),
            xytext=(2, 0),
            textcoords="offset points",
            fontsize=7,
            color="tab:red",
            fontweight="bold",
        )
        ax.axvline(at, color="tab:red", linewidth=1.2, alpha=0.8)
    names = [f"{n} @{plan.host_of(n)}" for n in managers] if colours else managers
    ax.set_yticks([0, *[lane[n] for n in managers]], ["calls", *names])
    ax.set_ylim(-0.7, len(managers) + 1.2)
    ax.set_xlim(0, end * 1.02 if end > 0 else 1)
    ax.grid(visible=True, axis="x", alpha=0.3)
    title = f"run {run.run} (seed {run.seed}, {run.verdict_counts()})"
    if value is not None:
        title = f"{results.plan.setting_label()} = {_label(results, value)}: {title}"
    summary = f"{run.calls_ok} calls ok, {run.calls_failed} failed, {run.restarts} restarts"
    if run.gave_up:
        summary += ", the supervisor gave up"
    ax.set_title(f"{title}; {summary}", fontsize=9, loc="left")
    ax.plot([], [], color="tab:red", alpha=0.6, linewidth=6, label="not serving")
    ax.scatter([], [], marker="^", color="tab:green", label="serves again")
    if not colours:
        ax.plot([], [], color="black", linestyle="--", linewidth=0.8, label="fault")
    for host, colour in colours.items():
        ax.plot([], [], color=colour, linestyle="--", linewidth=0.8, label=f"fault on host {host}")
    ax.scatter([], [], marker="|", color="tab:gray", label="call answered")
    ax.scatter([], [], marker="x", color="tab:red", label="call failed")
