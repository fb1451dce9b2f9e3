"""The package's public names (`rr_actors/__init__.py`): what `__all__` offers, and every
name it offered before still importable (issue 54 part 5)."""

from __future__ import annotations

import subprocess
import sys

import rr_actors
from rr_actors import config, errors


def python(*argv: str) -> subprocess.CompletedProcess[str]:
    """`python *argv` in a fresh interpreter, its output captured (a minute at most)."""
    return subprocess.run(
        [sys.executable, *argv], check=False, capture_output=True, text=True, timeout=60
    )


BEFORE_ISSUE_54 = [
    "MAX_DEPENDENCY_DEPTH",
    "Backoff",
    "CallTimeoutError",
    "CatalogCorruptError",
    "CatalogWriteError",
    "ChildCounts",
    "ChildInfo",
    "Claimant",
    "ConfigError",
    "DependencyCycleError",
    "DuplicateNameError",
    "DuplicateQueryIdError",
    "ErrorFrame",
    "InternalError",
    "ManagerSpec",
    "MessageTooLargeError",
    "MissingExtraError",
    "Query",
    "Registrar",
    "RegistrarConfig",
    "RegistrarStoppedError",
    "RegistrarUnavailableError",
    "ResourceLoadError",
    "ResourceRegistrar",
    "RrError",
    "Status",
    "StatusCallback",
    "StatusUpdate",
    "StatusWatch",
    "Subscription",
    "Supervisor",
    "SupervisorGaveUpError",
    "SupervisorSpec",
    "TransferError",
    "UnknownQueryError",
    "UnknownRegistrarError",
    "UnknownServerError",
    "ZenohNetwork",
    "ZenohTLS",
    "quarantine_backup",
]
"""`rr_actors.__all__` as it was (41 names): a program that imported any of them still can."""


def test_the_top_level_offers_at_most_25_names_each_of_them_defined() -> None:
    assert len(rr_actors.__all__) <= 25
    assert len(set(rr_actors.__all__)) == len(rr_actors.__all__)
    for name in rr_actors.__all__:
        assert getattr(rr_actors, name) is not None


def test_every_name_the_package_offered_before_still_imports() -> None:
    code = "\n".join(  # (a fresh interpreter: nothing imported before, `from` as a user writes)
        f"try:\n    from rr_actors import {name}\nexcept ImportError as e:\n    print(e)"
        for name in BEFORE_ISSUE_54
    )
    run = python("-c", code)

    assert (run.returncode, run.stdout, run.stderr) == (0, "", "")


def test_every_error_is_in_the_errors_module_and_the_same_class_at_the_top() -> None:
    for name in errors.__all__:
        assert getattr(rr_actors, name) is getattr(errors, name)


def test_the_dependency_depth_is_the_configs_and_the_same_at_the_top() -> None:
    assert rr_actors.MAX_DEPENDENCY_DEPTH is config.MAX_DEPENDENCY_DEPTH == 64


def test_quarantine_backup_is_beside_the_error_it_recovers_from_imported_at_first_use() -> None:
    """Out of the top's `__all__` (issue 54 part 5), in `rr_actors.errors` beside
    `CatalogCorruptError`: the store's function, which `import rr_actors.errors` leaves
    unimported until the name is used; `rr.quarantine_backup` still the same function."""
    code = (
        "import sys, rr_actors as rr, rr_actors.errors as errors\n"
        "print('rr_actors._store' in sys.modules, 'quarantine_backup' in rr.__all__)\n"
        "from rr_actors.errors import CatalogCorruptError, quarantine_backup\n"
        "from rr_actors._store.files import quarantine_backup as the_stores\n"
        "print(quarantine_backup is the_stores is rr.quarantine_backup,\n"
        "      'quarantine_backup' in errors.__all__, hasattr(errors, 'restore_backup'))"
    )
    run = python("-c", code)

    assert (run.returncode, run.stderr, run.stdout) == (0, "", "False False\nTrue True False\n")


def test_importing_the_package_leaves_the_runtime_and_the_events_to_their_first_use() -> None:
    """`import rr_actors` cost 1.35 s when it took the runtime and `events.kinds` with it
    (issue 54 part 7); now only the errors, the configuration and the status types (the
    figure, against `import pykka`, is in benchmarks/NOTES.md). A name of the runtime
    imports its module at first use (PEP 562)."""
    code = (
        "import sys, rr_actors\n"
        "heavy = ('rr_actors.events', 'rr_actors._registrar', 'rr_actors._supervision',\n"
        "         'rr_actors._core', 'rr_actors._store', 'rr_actors._transport', 'pykka',\n"
        "         'msgspec')\n"
        "print(sorted(m for m in sys.modules if m.startswith(heavy)))\n"
        "rr_actors.events.ChildRestarted, rr_actors.Supervisor\n"
        "print('rr_actors.events.kinds' in sys.modules, 'rr_actors._supervision' in sys.modules)"
    )
    run = python("-c", code)

    assert (run.returncode, run.stderr) == (0, "")
    assert "[]\nTrue True\n" == run.stdout


LAB_MODULES = ["experiments", "mission", "observe", "teach", "otel", "_cli", "_tools"]
"""The lab's modules that lived under `rr_actors` before they moved to `rr_actors_lab`."""


def test_the_lab_imports_under_its_former_names_as_the_same_modules() -> None:
    """The lab moved beside the runtime (issue 54 part 1); a program written before imports
    it as it did: `rr_actors.experiments` (and its submodules) is `rr_actors_lab.experiments`,
    one module, so one class whichever name imported it. Both orders, in a fresh process."""
    code = (
        "import importlib, sys\n"
        "import rr_actors\n"
        "from rr_actors.experiments.plan import PlanError as old\n"
        "from rr_actors_lab.experiments.plan import PlanError as new\n"
        "import rr_actors_lab.mission.config as new_config\n"
        "import rr_actors.mission.config as old_config\n"
        "from rr_actors import otel\n"
        f"for name in {LAB_MODULES!r}:\n"
        "    old_m = importlib.import_module('rr_actors.' + name)\n"
        "    new_m = importlib.import_module('rr_actors_lab.' + name)\n"
        "    print(name, old_m is new_m, sys.modules['rr_actors.' + name] is new_m)\n"
        "print(old is new, old_config is new_config, otel is sys.modules['rr_actors_lab.otel'])\n"
        "twins = [m for m in list(sys.modules) if m.startswith('rr_actors.experiments')]\n"
        "print(old.__module__, all(sys.modules[m] is sys.modules['rr_actors_lab' + m[9:]]\n"
        "                          for m in twins))\n"
    )
    run = python("-c", code)

    assert (run.returncode, run.stderr) == (0, "")
    assert [f"{name} True True" for name in LAB_MODULES] + [
        "True True True",
        "rr_actors_lab.experiments.plan True",
    ] == run.stdout.splitlines()


def test_the_runtime_runs_without_importing_the_lab() -> None:
    """A program that uses the runtime alone (a supervisor, a registrar, the events) never
    imports the lab: the runtime reads alone (issue 54 part 1)."""
    code = (
        "import sys, rr_actors as rr\n"
        "rr.Supervisor, rr.ResourceRegistrar, rr.events.ChildRestarted, rr.errors\n"
        "import rr_actors.testing\n"
        "print(sorted(m for m in sys.modules if m.startswith('rr_actors_lab')))\n"
    )
    run = python("-c", code)

    assert (run.returncode, run.stderr) == (0, "")
    assert "[]\n" == run.stdout


def test_a_former_lab_name_runs_with_dash_m_and_a_missing_one_is_named_as_asked() -> None:
    """`python -m rr_actors.mission` ran the demo before the move and still does; a module
    that does not exist is not found under the name the program asked for."""
    run = python("-m", "rr_actors.mission", "--help")
    missing = python("-c", "import rr_actors.experiments.no_such_module")

    assert (0, "") == (run.returncode, run.stderr)
    assert run.stdout.startswith("usage: rr-actors demo")
    assert "No module named 'rr_actors.experiments.no_such_module'" in missing.stderr
