"""The package's public names (`rr_actors/__init__.py`): what `__all__` offers, and every
name it offered before still importable (issue 54 part 5)."""

from __future__ import annotations

import rr_actors
from rr_actors import config, errors
from tests.support.python import python


def printed(code: str) -> str:
    """What `python -c code` printed, once it exited 0 with nothing on stderr."""
    run = python("-c", code, timeout=60)
    assert (run.returncode, run.stderr) == (0, "")
    return run.stdout


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
    assert "" == printed(code)


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
    assert "False False\nTrue True False\n" == printed(code)


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
    assert "[]\nTrue True\n" == printed(code)


LAB_MODULES = ["experiments", "mission", "observe", "teach", "otel"]
"""The lab's modules that lived under `rr_actors` before they moved to `rr_actors_lab`."""

HIDE_THE_LAB = (
    "import importlib.abc, sys\n"
    "class _NoLab(importlib.abc.MetaPathFinder):\n"
    "    def find_spec(self, name, path=None, target=None):\n"
    "        if name == 'rr_actors_lab' or name.startswith('rr_actors_lab.'):\n"
    "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
    "sys.meta_path.insert(0, _NoLab())\n"
)
"""The runtime installed alone: no module of `rr_actors_lab` imports."""


def test_the_lab_imports_under_its_former_names_with_a_warning_naming_the_new_one() -> None:
    """The lab moved beside the runtime (issue 54 part 1); a program written before runs on
    for one release: each name of `rr_actors.experiments` is `rr_actors_lab.experiments`'s,
    with a `DeprecationWarning` naming the new spelling (small alias modules, no import
    hook: issue 71), and a submodule imports from its one home (no second copy)."""
    code = (
        "import importlib, sys, warnings\n"
        "from rr_actors_lab.experiments.plan import PlanError as new\n"
        "import rr_actors_lab.mission.config as new_config\n"
        "with warnings.catch_warnings(record=True) as seen:\n"
        "    warnings.simplefilter('always')\n"
        "    from rr_actors.experiments import plan\n"
        "    from rr_actors.mission import config as old_config\n"
        "    import rr_actors.experiments as old\n"
        "    print(plan.PlanError is new, old_config is new_config, old.run is\n"
        "          importlib.import_module('rr_actors_lab.experiments').run)\n"
        f"    for name in {LAB_MODULES!r}:\n"
        "        importlib.import_module('rr_actors.' + name).__doc__\n"
        "print(sorted({str(w.message).split(' is ')[0] for w in seen}))\n"
        "print(all(w.category is DeprecationWarning for w in seen),\n"
        "      'use rr_actors_lab.experiments.run' in str(seen[-1].message))\n"
        "try:\n"
        "    import rr_actors.experiments.plan\n"
        "except ModuleNotFoundError as exc:\n"
        "    print(exc)\n"
        "print(sorted(m for m in sys.modules if m.startswith('rr_actors.experiments.')))\n"
    )
    assert [
        "True True True",
        "['rr_actors.experiments.plan', 'rr_actors.experiments.run', 'rr_actors.mission.config']",
        "True True",
        "No module named 'rr_actors.experiments.plan'; 'rr_actors.experiments' is not a package",
        "[]",
    ] == printed(code).splitlines()


def test_the_runtime_runs_without_importing_the_lab() -> None:
    """A program that uses the runtime alone (a supervisor, a registrar, the events) never
    imports the lab: the runtime reads alone (issue 54 part 1)."""
    code = (
        "import sys, rr_actors as rr\n"
        "rr.Supervisor, rr.ResourceRegistrar, rr.events.ChildRestarted, rr.errors\n"
        "import rr_actors.testing\n"
        "print(sorted(m for m in sys.modules if m.startswith('rr_actors_lab')))\n"
    )
    assert "[]\n" == printed(code)


def test_a_former_lab_name_runs_with_dash_m_with_a_warning_naming_the_new_one() -> None:
    """`python -m rr_actors.mission` ran the demo before the move and `python -m rr_actors`
    the command line: both still do for one release, each warning of its new name."""
    run = python("-m", "rr_actors.mission", "--help", timeout=60)
    runtime = python("-m", "rr_actors", "--help", timeout=60)

    assert run.returncode == 0
    assert run.stdout.startswith("usage: rr-actors demo")
    assert "DeprecationWarning: python -m rr_actors.mission is deprecated" in run.stderr
    assert "use python -m rr_actors_lab.mission" in run.stderr
    assert runtime.returncode == 0, runtime.stderr
    assert runtime.stdout.startswith("usage: rr-actors")
    assert "DeprecationWarning: python -m rr_actors is deprecated" in runtime.stderr
    assert "use python -m rr_actors_lab" in runtime.stderr


def test_the_runtime_works_with_the_lab_hidden_and_observe_names_its_extra() -> None:
    """The runtime installed alone (issue 71 item 1): `import rr_actors`, every public name,
    a supervisor's life and its errors, with no module of `rr_actors_lab` importable; the
    deprecated `sup.observe()` and `sup.graph()` raise `MissingExtraError` naming the
    extra, not a bare `ModuleNotFoundError`; nothing of the lab was imported."""
    code = HIDE_THE_LAB + (
        "import warnings\n"
        "warnings.simplefilter('ignore', DeprecationWarning)\n"
        "import rr_actors as rr, rr_actors.errors, rr_actors.config, rr_actors.testing\n"
        "for name in rr.__all__:\n"
        "    getattr(rr, name)\n"
        "rr.errors.quarantine_backup, rr.events.ChildRestarted\n"
        "with rr.Supervisor(rr.ManagerSpec('m')) as sup:\n"
        "    for call in (sup.observe, sup.graph):\n"
        "        try:\n"
        "            call()\n"
        "        except rr.MissingExtraError as exc:\n"
        "            print(type(exc).__name__, exc.extra, str(exc).splitlines()[0])\n"
        "print(sorted(m for m in sys.modules if m.startswith('rr_actors_lab')))\n"
    )
    lines = printed(code).splitlines()
    assert lines[0].startswith("MissingExtraError observe sup.observe() needs an extra")
    assert lines[1].startswith("MissingExtraError observe sup.graph() needs an extra")
    assert lines[2:] == ["[]"]


def test_the_spellings_that_moved_to_the_lab_warn_naming_the_new_one() -> None:
    """`sup.observe()`, `sup.graph()` and `rr_actors.__main__.main` work for one release,
    each with a `DeprecationWarning` that names its spelling in the lab."""
    code = (
        "import warnings, rr_actors as rr\n"
        "with warnings.catch_warnings(record=True) as seen:\n"
        "    warnings.simplefilter('always')\n"
        "    with rr.Supervisor(rr.ManagerSpec('m')) as sup:\n"
        "        text = sup.graph()\n"
        "        with sup.observe() as page:\n"
        "            print(page.url.startswith('http://127.0.0.1:'))\n"
        "    from rr_actors.__main__ import main\n"
        "    from rr_actors_lab.__main__ import main as new_main\n"
        "import rr_actors_lab.observe as lab\n"
        "print(main is new_main, 'flowchart' in text)\n"
        "for w in seen:\n"
        "    print(w.category.__name__, w.message)\n"
    )
    assert [
        "True",
        "True True",
        "DeprecationWarning sup.graph() is deprecated and goes in the next release: "
        "use rr_actors_lab.observe.graph(sup)",
        "DeprecationWarning sup.observe() is deprecated and goes in the next release: "
        "use rr_actors_lab.observe.observe(sup)",
        "DeprecationWarning rr_actors.__main__.main is deprecated and goes in the next "
        "release: use rr_actors_lab.__main__.main",
    ] == printed(code).splitlines()
