"""A newcomer who reads only the README or the docs' index starts the same way and finds
every tutorial; the index lists every how-to."""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TUTORIALS = sorted(p.name for p in (ROOT / "docs" / "tutorial").glob("*.md"))
HOW_TOS = sorted(p.name for p in (ROOT / "docs" / "how-to").glob("*.md"))


def first_block(page: Path) -> str:
    match = re.search(r"```bash\n(.*?)```", page.read_text(), re.DOTALL)
    assert match is not None, f"{page} has no bash block"
    return match.group(1)


def test_the_docs_index_starts_with_the_readmes_two_commands() -> None:
    index = (ROOT / "docs" / "index.md").read_text().splitlines()

    assert index[2] == "```bash"  # right under the title, as in the README
    assert first_block(ROOT / "README.md") == first_block(ROOT / "docs" / "index.md")


@pytest.mark.parametrize("tutorial", TUTORIALS)
def test_every_tutorial_is_linked_from_the_index_and_the_readme(tutorial: str) -> None:
    index = (ROOT / "docs" / "index.md").read_text()
    where_next = index[index.index("## Where to go next") :]
    readme = (ROOT / "README.md").read_text()

    assert f"(tutorial/{tutorial})" in where_next
    assert f"(docs/tutorial/{tutorial})" in readme


@pytest.mark.parametrize("how_to", HOW_TOS)
def test_every_how_to_is_linked_from_the_index(how_to: str) -> None:
    index = (ROOT / "docs" / "index.md").read_text()
    where_next = index[index.index("## Where to go next") :]

    assert f"(how-to/{how_to})" in where_next


def test_the_experiment_tutorial_runs_the_readmes_experiment_command() -> None:
    """A reader who follows the tutorial after the README runs what the README runs
    (`--force` was in the README's command only, issue 44 item 7)."""
    command = re.compile(r"^rr-actors experiment \w.*$", re.MULTILINE)
    readme = command.findall((ROOT / "README.md").read_text())
    tutorial = command.findall((ROOT / "docs" / "tutorial" / "first-experiment.md").read_text())

    assert ["rr-actors experiment first --out first-results --force"] == readme
    assert set(readme) <= set(tutorial)


def test_the_plan_for_the_docs_toolchain_is_a_page_of_the_site() -> None:
    """mkdocs-material's end of life (May 2027): the plan, and why, is recorded in
    `docs/` and listed in the site's navigation (issue 44 item 7)."""
    page = (ROOT / "docs" / "explanation" / "docs-toolchain.md").read_text()

    assert "explanation/docs-toolchain.md" in (ROOT / "mkdocs.yml").read_text()
    assert "**The plan:" in page
    assert "May 2027" in page


def test_each_time_of_the_second_command_says_when_and_at_which_commit_it_was_measured() -> None:
    """The index's table of the README's second command: a time says the day and the
    commit it was measured at, or that it was not measured; `benchmarks/bench_setup.py`
    measures a row (issue 44 items 6 and 8: "(to measure)", and times of a suite a third
    smaller than today's given as today's)."""
    index = (ROOT / "docs" / "index.md").read_text().splitlines()
    header = index.index(
        "| the second command's step | quiet | two CPU-bound processes beside it |"
    )
    rows = list(itertools.takewhile(lambda line: line.startswith("|"), index[header + 2 :]))
    cells = [cell.strip() for row in rows for cell in row.strip("|").split("|")[1:]]
    measured = re.compile(r".*\(\d{4}-\d\d-\d\d, `[0-9a-f]{7,40}`(, [^)]*)?\)")

    assert 2 == len(rows)
    assert [] == [c for c in cells if c != "not measured yet" and not measured.fullmatch(c)]
    assert "python benchmarks/bench_setup.py --busy 2" in "\n".join(index)
