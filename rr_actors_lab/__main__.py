"""`python -m rr_actors_lab`: the `rr-actors` command line (docs/reference/cli.md).

`main(argv, out)` is the public way to run a command in this process (the console script
`rr-actors` and `python -m rr_actors_lab` call it with the process's arguments):

    from rr_actors_lab.__main__ import main
    code = main(["inspect", "state/erm.db", "--json"])

`build_parser()` gives the command line's `argparse` parser (to read a command's
arguments the way `rr-actors` does, e.g. before running it with a seam of your own).
"""

from __future__ import annotations

from rr_actors_lab._cli import build_parser, main

__all__ = ["build_parser", "main"]

if __name__ == "__main__":
    raise SystemExit(main())
