"""`rr_actors_lab.mission.stderr`: what any process of the demo writes to standard error while
the live progress line shows, on a real terminal (a pseudo-terminal of 80 columns).

The program under test is a user's, run as one: the demo's own output (`make_output` on
the terminal) and a real manager process whose log is not configured.
"""

from __future__ import annotations

import itertools
import sys
import textwrap
from pathlib import Path

import pytest

from tests.support.terminal import on_a_terminal

MANAGER_WRITES = textwrap.dedent(
    """
    import logging, sys
    import rr_actors as rr
    from rr_actors_lab.mission.output import Progress, make_output

    def setup(erm):  # in the manager's process, logging not configured: to its stderr
        logging.getLogger("rr_actors").warning(
            "manager %s: %s", erm.name, "a line of a manager's process " * 6
        )
        erm.register_server("echo", load=lambda r: r, unload=lambda r, s: None)

    if __name__ == "__main__":
        with make_output(sys.stdout) as output:
            output.progress(Progress(1.0, 2.0, 16.0, True, "F3: cm killed"))
            with rr.Supervisor([rr.ManagerSpec("erm", setup, isolation="process")]):
                output.story("[  1.00 s] erm is up")
    """
)


@pytest.mark.timeout(120)
def test_a_line_another_process_writes_under_the_progress_line_starts_a_line_and_wraps(
    tmp_path: Path,
) -> None:
    """A manager process writes to the demo's terminal while the progress line shows
    (its WARNING, before its setup sends the log to the run's file): the line goes above
    the progress line and wraps at words, instead of running on from the progress line's
    end, 80 columns plus its own (121 in a loaded CI run of `--step`; issue 44 item 2)."""
    code, text = on_a_terminal(
        [sys.executable, "-c", MANAGER_WRITES], columns=80, timeout=90, cwd=tmp_path
    )

    lines = text.splitlines()  # (at \r too: the progress line is redrawn after one)
    wide = [f"[{len(line)}] {line}" for line in lines if len(line) > 80]
    assert 0 == code, text
    assert [] == wide, "lines over 80 columns:\n" + "\n".join(wide)
    start = next(i for i, line in enumerate(lines) if line.startswith("WARNING rr_actors: "))
    record = [
        lines[start],
        *itertools.takewhile(lambda x: x.startswith("    "), lines[start + 1 :]),
    ]
    said = "WARNING rr_actors: manager erm: " + "a line of a manager's process " * 6
    assert " ".join(said.split()) == " ".join(" ".join(record).split())
    assert any(line.startswith("[  1.00 s] erm is up") for line in lines)
