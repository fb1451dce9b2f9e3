"""Run the Python blocks of one docs page in one namespace, as a reader pasting them would.

`tests/test_docs.py` starts this as a program in the page's working directory and feeds it
the page's Python blocks one by one, in page order, as JSON lines on standard input
(`{"code": ..., "filename": ...}`). Each block runs with `exec` in one shared namespace
whose `__name__` is `"__main__"`, so later blocks see what earlier blocks defined, and
`if __name__ == "__main__":` guards run as in a script. After each block one JSON line goes
to the file descriptor named by `argv[1]`: `{"ok": true}`, or `{"ok": false, "error":
<traceback>}`. The block's own output goes to this program's standard output and error;
its input is empty, as a script's run with `< /dev/null` (an `input()` raises `EOFError`:
a page's "press Enter to stop" ends at once).

At the end of its input it writes one more line, `{"left": [...]}`: the registrars and
supervisors the page left running (which the interpreter would stop as it exits: see
`rr_actors._core.exit`), and returns; the test fails a page that leaves any, or that
leaves anything else that keeps the interpreter from exiting.
"""

from __future__ import annotations

import io
import json
import os
import sys
import traceback
from typing import Any


def main() -> None:
    """Run every block that arrives on standard input; answer each on `argv[1]`."""
    replies = os.fdopen(int(sys.argv[1]), "w", buffering=1)
    namespace: dict[str, Any] = {"__name__": "__main__", "__builtins__": __builtins__}
    source, sys.stdin = sys.stdin, io.StringIO()  # a block reads no input (as `< /dev/null`)
    for line in source:
        block = json.loads(line)
        try:
            exec(compile(block["code"], block["filename"], "exec"), namespace)  # noqa: S102
        except BaseException:  # SystemExit and KeyboardInterrupt are reported too
            reply = {"ok": False, "error": traceback.format_exc()}
        else:
            reply = {"ok": True}
        sys.stdout.flush()
        sys.stderr.flush()
        replies.write(json.dumps(reply) + "\n")
    left: list[str] = []
    if "rr_actors" in sys.modules:  # (a page that never imported it left none)
        from rr_actors._core.exit import left_running  # noqa: PLC0415

        left = left_running()
    replies.write(json.dumps({"left": left}) + "\n")
    replies.close()


if __name__ == "__main__":
    main()
