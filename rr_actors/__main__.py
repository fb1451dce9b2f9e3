"""`python -m rr_actors`: the `rr-actors` command line (docs/reference/cli.md).

`main(argv, out)` is the public way to run a command in this process (the console script
`rr-actors` and `python -m rr_actors` call it with the process's arguments):

    from rr_actors.__main__ import main
    code = main(["inspect", "state/erm.db", "--json"])
"""

from __future__ import annotations

from rr_actors._cli import main

__all__ = ["main"]

if __name__ == "__main__":
    raise SystemExit(main())
