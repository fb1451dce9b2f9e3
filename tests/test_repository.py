"""The repository itself: what the README's commands write when run from a checkout."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
GIT = shutil.which("git")


@pytest.mark.skipif(GIT is None or not (ROOT / ".git").exists(), reason="not a git checkout")
@pytest.mark.parametrize(
    "written",
    [
        "rr-actors-demo/report.json",  # rr-actors demo
        "state/erm.db",  # the README's supervisor snippet
        "first-results/runs.csv",  # the README's experiment command
        "results/runs.csv",  # the experiment tutorial's
    ],
)
def test_what_the_readme_and_tutorials_write_is_ignored_by_git(written: str) -> None:
    result = subprocess.run(
        [str(GIT), "check-ignore", "--quiet", "--no-index", written],
        cwd=ROOT,
        capture_output=True,
        timeout=30,
        check=False,
    )

    assert 0 == result.returncode, f"{written} is not in .gitignore"


def test_no_module_of_the_package_imports_itself_back() -> None:
    """No import circle between modules, even through an import for a type only (issue 31)."""
    grimp = pytest.importorskip("grimp")  # (installed with import-linter: the dev extra)
    graph = grimp.build_graph("rr_actors", exclude_type_checking_imports=False)
    circles = set()
    for importer in graph.modules:
        for imported in graph.find_modules_directly_imported_by(importer):
            back = graph.find_shortest_chain(importer=imported, imported=importer)
            if back is not None:  # the circle, from its first module in order
                circle = (importer, *back[:-1])
                start = circle.index(min(circle))
                circles.add(" -> ".join(circle[start:] + circle[: start + 1]))

    assert [] == sorted(circles)


MARKERS = ("<<<<<<< ", ">>>>>>> ")
"""How a merge conflict left in a file starts its lines (git's markers)."""


def test_no_file_holds_a_merge_conflict_left_in_it() -> None:
    # One was committed in the architecture page's message table and no build saw it:
    # markdown renders the markers as text.
    roots = [ROOT / name for name in ("docs", "rr_actors", "tests", "benchmarks", "examples")]
    files = [p for root in roots for p in root.rglob("*") if p.suffix in {".md", ".py", ".toml"}]
    files += [p for p in ROOT.iterdir() if p.suffix in {".md", ".toml"}]
    assert len(files) > 100  # the walk found the tree
    left = [
        f"{path.relative_to(ROOT)}:{number}"
        for path in files
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if line.startswith(MARKERS)
    ]
    assert [] == left


OF_THE_HANDLE = {
    "test_seams.py": "the seams of `rr_actors.testing` (`testing/seams.py`) on a registrar",
    "test_registrar_bad_input.py": "the handle's checks of its arguments",
    "test_registrar_names.py": "the names a handle starts a registrar with",
}
"""Registrar test modules named for the handle's surface, not for a module (issue 41 item 4
regroups the handle)."""


def test_each_registrar_test_module_is_named_for_the_module_it_tests() -> None:
    # One test module per runtime module (issue 41 item 5): a finding is a test in the
    # module of what it tests, a scenario a class there, never a new file.
    modules = {path.stem for path in (ROOT / "rr_actors" / "_registrar").glob("*.py")}
    tests = sorted(path.name for path in (ROOT / "tests" / "registrar").glob("test_*.py"))
    unnamed = [
        name
        for name in tests
        if name.removeprefix("test_").removesuffix(".py") not in modules
        and name not in OF_THE_HANDLE
    ]

    assert [] == unnamed


def test_each_transport_test_module_is_named_for_the_module_it_tests() -> None:
    # The module's path in the layer, "/" as "_": test_unix_link.py tests unix/link.py,
    # test_zenoh_ops_gate.py zenoh/ops/gate.py, test_base.py the contract (issue 41 item 5).
    transport = ROOT / "rr_actors" / "_transport"
    modules = {
        "_".join(path.relative_to(transport).with_suffix("").parts)
        for path in transport.rglob("*.py")
        if path.name != "__init__.py"
    }
    modules.add("memory")  # the in-memory carrier, `rr_actors/testing/memory.py`
    tests = sorted(path.name for path in (ROOT / "tests" / "transport").glob("test_*.py"))
    unnamed = [
        name for name in tests if name.removeprefix("test_").removesuffix(".py") not in modules
    ]

    assert [] == unnamed
