"""rr_actors chooses how manager processes start; `set_start_method` does not change it.

Documented in the supervision tutorial: managers start from the forkserver (spawn where
there is none), never from a fork of the threaded parent, whatever the program set with
`multiprocessing.set_start_method`.
"""

from __future__ import annotations

import multiprocessing
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent(
    """
    import multiprocessing, os
    import rr_actors as rr

    def main():
        multiprocessing.set_start_method({method!r})
        sup = rr.Supervisor([rr.ManagerSpec("m", lambda r: None, isolation="process")])
        with sup:
            parent = sup.run_in("m", lambda registrar: os.getppid())
        print("forked by this process" if parent == os.getpid() else "forked elsewhere")

    if __name__ == "__main__":
        main()
    """
)


@pytest.mark.skipif(
    "forkserver" not in multiprocessing.get_all_start_methods(), reason="needs a forkserver"
)
@pytest.mark.parametrize("method", ["spawn", "fork"])
def test_a_start_method_set_by_the_program_does_not_change_how_managers_start(
    method: str,
) -> None:
    result = subprocess.run(
        [sys.executable, "-c", SCRIPT.format(method=method)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )

    assert (0, "forked elsewhere\n") == (result.returncode, result.stdout), result.stderr
