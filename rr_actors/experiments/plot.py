"""The experiment's figures: recovery times per compared value, and timelines of runs.

Needs matplotlib (`pip install 'rr-actors[experiments]'`); importing this module without
it raises `ImportError`, which `run` takes as "no plots".
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import matplotlib as mpl

mpl.use("Agg")  # no display needed
import matplotlib.pyplot as plt

from rr_actors.experiments.results import Results, RunResult, show_value

__all__ = ["plot_recovery", "plot_timeline"]

_SHORT = {
    "kill_manager": "kill",
    "kill_resource": "kill proc",
    "hang_manager": "hang",
    "load_error": "load err",
    "cut_connections": "cut",
}


def _label(results: Results, value: Any) -> str:
    return results.plan.tree.strategy if value is None else show_value(value)


def plot_recovery(results: Results, path: Path) -> None:
    """Box plots per compared value: recovery per fault, downtime and failed calls per run.

    Args:
        results: the experiment's results.
        path: the PNG file to write.
    """
    groups = [(value, runs) for value, runs in results.by_value() if runs]
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
    fig, axes = plt.subplots(
        1, 3, figsize=(12, 4.2), dpi=110, gridspec_kw={"width_ratios": [3, 2, 2]}
    )
    try:
        jitter = random.Random(0)  # noqa: S311 - where dots go, not a secret
        for ax, (data, colour, ylabel, title) in zip(axes, panels, strict=True):
            ax.boxplot(
                [d if d else [float("nan")] for d in data],
                showfliers=False,
                medianprops={"color": colour, "linewidth": 2},
            )
            ax.set_xticks(range(1, len(labels) + 1), labels)
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


def _verdicts(results: Results) -> str:
    kinds = ("held", "violated", "unverifiable")
    counts = {k: sum(1 for r in results.runs if r.verdict == k) for k in kinds}
    return ", ".join(f"{counts[k]} {k}" for k in kinds)


def _first_runs(results: Results) -> list[tuple[Any, RunResult]]:
    """The first run of each compared value (at most four)."""
    return [(value, runs[0]) for value, runs in results.by_value() if runs][:4]


def plot_timeline(results: Results, path: Path) -> None:
    """One timeline per compared value (its first run): downtime, restarts, faults, calls.

    Args:
        results: the experiment's results.
        path: the PNG file to write.
    """
    shown = _first_runs(results)
    managers = [m.name for m in results.plan.managers()]
    rows = len(managers) + 1
    fig, axes = plt.subplots(
        len(shown), 1, figsize=(10, 1.5 + 0.42 * rows * len(shown)), dpi=110, squeeze=False
    )
    try:
        for (value, run), ax in zip(shown, axes[:, 0], strict=True):
            _timeline(ax, results, value, run, managers)
        axes[-1, 0].set_xlabel("seconds since the workload started")
        handles, labels = axes[0, 0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8)
        fig.tight_layout(rect=(0, 0.35 / fig.get_figheight(), 1, 1))
        fig.savefig(path)
    finally:
        plt.close(fig)


def _timeline(ax: Any, results: Results, value: Any, run: RunResult, managers: list[str]) -> None:
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
        ax.axvline(fault.injected_s, color="black", linestyle="--", linewidth=0.8, alpha=0.7)
        if fault.injected_s - labelled < end / 14:
            continue  # no room for another label here
        labelled = fault.injected_s
        ax.annotate(
            f"{_SHORT.get(fault.kind, fault.kind)} {fault.target or ''}".strip(),
            (fault.injected_s, len(managers) + 0.55),
            xytext=(2, 0),
            textcoords="offset points",
            fontsize=7,
            va="bottom",
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
    ax.set_yticks([0, *[lane[n] for n in managers]], ["calls", *managers])
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
    ax.plot([], [], color="black", linestyle="--", linewidth=0.8, label="fault")
    ax.scatter([], [], marker="|", color="tab:gray", label="call answered")
    ax.scatter([], [], marker="x", color="tab:red", label="call failed")
