"""Every code block in README.md and docs/ runs, or says why it cannot.

One test per page. The page's fenced blocks are taken in page order, in a fresh temporary
working directory for the page (with `examples/` linked into it, so the commands read as
written):

- `python` blocks run one after the other in one interpreter (`tests/support/docs_kernel.py`), as
  if pasted into one session: a later block sees what earlier ones defined, and
  `__name__` is `"__main__"`; their input is empty (`input()` raises `EOFError`). After
  the last block nothing may be left running: a page that leaves a registrar or a
  supervisor running fails, and the interpreter must exit.
  A block that is only a snippet include (`--8<-- "examples/x.py"`) is the example
  itself: the file must exist and a test in `tests/` must run it by name
  (`test_examples.py` runs every example).
- `bash` blocks run command by command (`&&` and line breaks separate commands; `#`
  starts a comment):
    - `rr-actors ...` runs the installed console script; `python examples/...` and
      `python -m rr_actors...` run with this interpreter. Each must exit with 0 within
      `COMMAND_TIMEOUT`. The same command twice on a page runs once. `rr-actors demo`
      without `--fast` runs with `--fast` (the same mission, shorter: the full one takes
      about 35 s).
    - `openssl ...` runs the system's `openssl` (`.ci/run` installs it) the same way, in
      the page's directory: a page's certificate recipes make real files, which its later
      blocks (and `tests/transport/zenoh/ops/test_tls.py`) check.
    - `pip install -e .[EXTRAS]` is not run: every extra it names must exist in
      `pyproject.toml`.
    - `python -m pytest -q ...` is not run (it is this very run): it must be the test
      command of `.ci/run`.
    - `apt-get update` and `apt-get install -y PKG...` are not run (they need root and the
      network): `.ci/run` must install every package named the same way.
    - `python benchmarks/X.py ...` is not run (benchmarks take minutes and are not tests):
      the script must exist and accept every option shown (it appears in its source).
    - anything else fails the test, unless the block is marked (below).
- `text`, `json` and `mermaid` blocks are output and data: not run. `toml` blocks are data too, but
  must parse (`tomllib`), and one that is a whole experiment plan (it has `duration` and
  `[tree]`) must be a valid plan; a `toml` block that is only a snippet include
  (`--8<-- "examples/experiments/x.toml"`) is checked as that file. A block without a
  language fails (say which it is).

A block that cannot run as shown carries a visible marker on the line right above its
fence (blank lines and other HTML comments may come between), with the reason:

    <!-- docs-test: skip: start() and stop() stand for your own code -->

A marker without a reason, or one that is not followed by a block, fails the test.

A page that shows an example (`--8<-- "examples/x.py"`) also links to its file by its
path in the repository; one test builds the site (`mkdocs build --strict`) and follows
those links to the examples' copies in it (`docs/hooks/examples.py`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import itertools
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import sysconfig
import tomllib
import types
from collections.abc import Iterator
from pathlib import Path

import pytest

import rr_actors
from rr_actors import errors
from rr_actors_lab.experiments import parse_plan
from tests.support import selecting

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", *sorted((ROOT / "docs").rglob("*.md"))]
KERNEL = Path(__file__).resolve().parent / "support" / "docs_kernel.py"

BLOCK_TIMEOUT = 60.0
"""Seconds one Python block may take."""

COMMAND_TIMEOUT = 120.0
"""Seconds one shell command may take."""

EXIT_TIMEOUT = 30.0
"""Seconds the page's interpreter gets to exit after its last block."""

PYTHON = ("python", "py", "python3")
SHELL = ("bash", "sh", "shell", "console")
DATA = ("text", "json", "mermaid")
TOML = ("toml",)

FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})[ \t]*(?P<info>[^`]*)$")
MARKER = re.compile(r"^\s*<!--\s*docs-test:\s*(?P<body>.*?)\s*-->\s*$")
COMMENT = re.compile(r"^\s*<!--.*-->\s*$")
SNIPPET = re.compile(r'^--8<--\s+"(?P<path>[^"]+)"\s*$')


@dataclasses.dataclass(frozen=True)
class Block:
    """One fenced code block of a page.

    Attributes:
        page: the Markdown file.
        line: 1-based line number of the opening fence.
        lang: the first word of the info string (`""` if none).
        code: the content, with the fence's indentation removed.
        skip: the reason of a `docs-test: skip:` marker above it, else `None`.
    """

    page: Path
    line: int
    lang: str
    code: str
    skip: str | None

    @property
    def where(self) -> str:
        return f"{rel(self.page)}:{self.line}"


def rel(page: Path) -> str:
    """`page` relative to the repository (as it is named in failures)."""
    return str(page.relative_to(ROOT)) if page.is_relative_to(ROOT) else str(page)


def parse_marker(body: str, where: str) -> str:
    """The reason of a marker's body `skip: REASON`."""
    kind, _, reason = body.partition(":")
    if kind.strip() != "skip" or len(reason.split()) < 3:
        pytest.fail(f"{where}: a marker reads `docs-test: skip: <why, in a few words>`: {body!r}")
    return reason.strip()


def blocks(page: Path) -> list[Block]:
    """The fenced blocks of `page`, in order, with their markers."""
    lines = page.read_text().splitlines()
    found: list[Block] = []
    pending: tuple[int, str] | None = None  # a marker waiting for its block
    i = 0
    while i < len(lines):
        line = lines[i]
        marker = MARKER.match(line)
        if marker is not None:
            if pending is not None:
                pytest.fail(f"{rel(page)}:{pending[0]}: a marker without a block")
            pending = (i + 1, parse_marker(marker.group("body"), f"{rel(page)}:{i + 1}"))
            i += 1
            continue
        opening = FENCE.match(line)
        if opening is None:
            if pending is not None and line.strip() and not COMMENT.match(line):
                pytest.fail(f"{rel(page)}:{pending[0]}: a marker without a block")
            i += 1
            continue
        indent, fence = opening.group("indent"), opening.group("fence")
        info = opening.group("info").split()
        content: list[str] = []
        j = i + 1
        while j < len(lines):
            stripped = lines[j].strip()
            if stripped.startswith(fence) and set(stripped) == {fence[0]}:
                break
            content.append(lines[j].removeprefix(indent))
            j += 1
        found.append(
            Block(
                page,
                i + 1,
                info[0] if info else "",
                "\n".join(content) + "\n",
                pending[1] if pending else None,
            )
        )
        pending = None
        i = j + 1
    if pending is not None:
        pytest.fail(f"{rel(page)}:{pending[0]}: a marker without a block")
    return found


# -- the page's interpreter ------------------------------------------------------------------


class Kernel:
    """`tests/support/docs_kernel.py` in `cwd`: one namespace for the page's Python blocks."""

    def __init__(self, cwd: Path) -> None:
        self.cwd = cwd
        self.log = cwd / ".docs-kernel.log"
        read_end, write_end = os.pipe()
        with self.log.open("w") as log:
            self.proc = subprocess.Popen(
                [sys.executable, str(KERNEL), str(write_end)],
                cwd=cwd,
                stdin=subprocess.PIPE,
                stdout=log,
                stderr=subprocess.STDOUT,
                text=True,
                pass_fds=(write_end,),
                start_new_session=True,  # its own process group: killed together if stuck
            )
        os.close(write_end)
        self.replies = os.fdopen(read_end, "r")

    def output(self) -> str:
        return self.log.read_text()[-4000:]

    def run(self, block: Block, code: str) -> None:
        """Run `code` (the block's); fail the test with the traceback if it raises."""
        assert self.proc.stdin is not None
        # Line numbers in a traceback are the page's: pad the code down to the block.
        padded = "\n" * block.line + code
        self.proc.stdin.write(json.dumps({"code": padded, "filename": str(block.page)}) + "\n")
        self.proc.stdin.flush()
        ready, _, _ = selecting.select([self.replies], [], [], BLOCK_TIMEOUT)
        if not ready:
            self.kill()
            pytest.fail(f"{block.where}: no answer within {BLOCK_TIMEOUT:g} s\n{self.output()}")
        line = self.replies.readline()
        if not line:
            self.kill()
            pytest.fail(f"{block.where}: the interpreter died\n{self.output()}")
        reply = json.loads(line)
        if not reply["ok"]:
            self.kill()
            pytest.fail(f"{block.where} raised:\n{reply['error']}\noutput:\n{self.output()}")

    def finish(self, page: Path) -> None:
        """End the input; nothing may be left running, and the interpreter must exit."""
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        ready, _, _ = selecting.select([self.replies], [], [], EXIT_TIMEOUT)
        left = json.loads(self.replies.readline() or "{}").get("left") if ready else None
        if left:
            self.kill()
            pytest.fail(f"{rel(page)}: its Python blocks leave something running: {left}")
        try:
            code = self.proc.wait(EXIT_TIMEOUT)
        except subprocess.TimeoutExpired:
            self.kill()
            pytest.fail(
                f"{rel(page)}: its Python blocks leave something running: the "
                f"interpreter did not exit within {EXIT_TIMEOUT:g} s\n{self.output()}"
            )
        finally:
            self.replies.close()
        assert 0 == code, self.output()

    def kill(self) -> None:
        """SIGKILL the interpreter's process group (it and what it started directly)."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(EXIT_TIMEOUT)
        if self.proc.stdin is not None:
            with contextlib.suppress(BrokenPipeError):
                self.proc.stdin.close()
        self.replies.close()


# -- commands ----------------------------------------------------------------------------------


def commands(code: str) -> Iterator[list[str]]:
    """The commands of a shell block: lines joined at `\\`, split at `&&`, comments dropped."""
    text = code.replace("\\\n", " ")
    for line in text.splitlines():
        words = shlex.split(line, comments=True)
        command: list[str] = []
        for word in words:
            if word == "&&":
                if command:
                    yield command
                command = []
            else:
                command.append(word)
        if command:
            yield command


def extras() -> set[str]:
    return set(
        tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    )


def ci_test_command() -> str:
    """The test command `.ci/run` runs (the line that runs pytest)."""
    for line in (ROOT / ".ci" / "run").read_text().splitlines():
        if line.startswith("python -m pytest"):
            return line.split("||")[0].strip()
    pytest.fail(".ci/run does not run `python -m pytest`")


def check_pip(block: Block, command: list[str]) -> None:
    """`pip install -e .[extras]`: not run; the extras must exist."""
    assert command[:3] == ["pip", "install", "-e"], f"{block.where}: {shlex.join(command)}"
    match = re.fullmatch(r"\.(?:\[(?P<extras>[\w,-]+)\])?", command[3])
    assert match is not None, f"{block.where}: installs {command[3]!r}, not this project"
    named = set((match.group("extras") or "").split(",")) - {""}
    assert named <= extras(), f"{block.where}: no such extra(s) {named - extras()}"


def check_apt(block: Block, command: list[str]) -> None:
    """`apt-get update`, `apt-get install -y PKG...`: not run; `.ci/run` installs them too."""
    if command[1:] == ["update"]:
        return
    assert command[1:3] == ["install", "-y"], f"{block.where}: {shlex.join(command)}"
    ci = (ROOT / ".ci" / "run").read_text()
    missing = [p for p in command[3:] if not re.search(rf"apt-get install -y .*\b{p}\b", ci)]
    assert [] == missing, f"{block.where}: .ci/run does not install {missing}"


def check_benchmark(block: Block, command: list[str]) -> None:
    """`python benchmarks/X.py ...`: not run; the script must exist and know the options.

    For `alternate.py ... -- Y.py ...`, the options after `--` are `Y.py`'s.
    """
    script = ROOT / command[1]
    assert script.is_file(), f"{block.where}: {command[1]} does not exist"
    options = command[2:]
    if "--" in options:
        options, inner = options[: options.index("--")], options[options.index("--") + 1 :]
        check_benchmark(block, ["python", f"benchmarks/{inner[0]}", *inner[1:]])
    source = script.read_text()
    if "import _harness" in source:  # (its --rounds, --batch, --quick)
        source += (script.parent / "_harness.py").read_text()
    unknown = [w for w in options if w.startswith("--") and w.split("=")[0] not in source]
    assert [] == unknown, f"{block.where}: {command[1]} has no option(s) {unknown}"


def run_command(block: Block, command: list[str], cwd: Path) -> None:
    """Run one command where the page's blocks run; fail the test unless it exits with 0."""
    if command[0] == "rr-actors":
        argv = [str(Path(sysconfig.get_path("scripts")) / "rr-actors"), *command[1:]]
    elif command[0] == "openssl":
        openssl = shutil.which("openssl")
        assert openssl is not None, f"{block.where}: no openssl (.ci/run installs it)"
        argv = [openssl, *command[1:]]
    else:
        argv = [sys.executable, *command[1:]]
    result = subprocess.run(
        argv,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=COMMAND_TIMEOUT,
        check=False,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert 0 == result.returncode, (
        f"{block.where}: `{shlex.join(command)}` exited with {result.returncode}\n"
        f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    )


def runnable(command: list[str]) -> list[str] | None:
    """The command as the test runs it, if it is one the test runs."""
    if command[0] == "openssl":
        return command
    if command[0] == "rr-actors":
        if command[1:2] == ["demo"] and "--fast" not in command:
            return [*command, "--fast"]
        return command
    if command[0] == "python" and len(command) > 1:
        if command[1].startswith("examples/"):
            return command
        if command[1] == "-m" and command[2:3] and command[2].startswith("rr_actors"):
            return command
    return None


def shell_block(block: Block, cwd: Path, done: set[tuple[str, ...]]) -> None:
    """Run or check every command of a shell block (see the module docstring)."""
    for written in commands(block.code):
        # pinned to a CPU (`taskset -c 0 ...`) or at real-time priority (`chrt -f 10
        # ...`): the command after it
        prefixed = written[:2] in (["taskset", "-c"], ["chrt", "-f"])
        command = written[3:] if prefixed else written
        if command[0] == "pip":
            check_pip(block, command)
            continue
        if command[0] == "apt-get":
            check_apt(block, command)
            continue
        if command[:3] == ["python", "-m", "pytest"]:
            assert shlex.join(command) == ci_test_command(), f"{block.where}: not CI's tests"
            continue
        if command[0] == "python" and command[1:2] and command[1].startswith("benchmarks/"):
            check_benchmark(block, command)
            continue
        argv = runnable(command)
        if argv is None:
            pytest.fail(
                f"{block.where}: `{shlex.join(command)}` is not a command this test runs; "
                "make the block runnable or mark it `<!-- docs-test: skip: <why> -->`"
            )
        if tuple(argv) not in done:
            done.add(tuple(argv))
            run_command(block, argv, cwd)


def toml_block(block: Block) -> None:
    """A `toml` block parses; a whole experiment plan in it is valid (see the docstring)."""
    text, source = block.code, block.where
    include = SNIPPET.match(text.strip())
    if include is not None:
        path = ROOT / include.group("path")
        assert path.is_file(), f"{block.where}: includes {path}, which does not exist"
        text, source = path.read_text(), str(path)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        pytest.fail(f"{source}: not TOML: {exc}")
    if "duration" in data and "tree" in data:
        parse_plan(text, source=source)


def python_block(block: Block) -> str | None:
    """The code to run for a Python block, or `None` for a snippet include (checked here)."""
    first = block.code.strip()
    include = SNIPPET.match(first)
    if include is None:
        return block.code
    path = include.group("path")
    assert (ROOT / path).is_file(), f"{block.where}: includes {path}, which does not exist"
    runners = [
        p.name for p in (ROOT / "tests").rglob("test_*.py") if Path(path).name in p.read_text()
    ]
    assert runners, f"{block.where}: no test in tests/ runs {path}"
    return None


@pytest.mark.timeout(300)
@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_every_code_block_of_the_page_runs_or_says_why_not(page: Path, tmp_path: Path) -> None:
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    kernel: Kernel | None = None
    done: set[tuple[str, ...]] = set()
    try:
        for block in blocks(page):
            if block.skip is not None or block.lang in DATA:
                continue
            if block.lang in PYTHON:
                code = python_block(block)
                if code is not None:
                    kernel = kernel or Kernel(tmp_path)
                    kernel.run(block, code)
            elif block.lang in SHELL:
                shell_block(block, tmp_path, done)
            elif block.lang in TOML:
                toml_block(block)
            elif not block.lang:
                pytest.fail(f"{block.where}: say what the block is (python, bash, text, ...)")
            else:
                pytest.fail(f"{block.where}: blocks in {block.lang!r} are not checked")
        if kernel is not None:
            kernel.finish(page)
    finally:
        if kernel is not None and kernel.proc.poll() is None:
            kernel.kill()


# -- the checker itself, and what the README promises -------------------------------------------


def test_the_checker_finds_blocks_markers_and_snippets(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text(
        "# t\n\n```python\nx = 1\n```\n\n<!-- docs-test: skip: needs a camera here -->\n"
        "<!-- fmt: off -->\n\n```bash\nrm -rf /\n```\n\n  ~~~text\n  out\n  ~~~\n"
    )

    found = blocks(page)

    assert [("python", None), ("bash", "needs a camera here"), ("text", None)] == [
        (b.lang, b.skip) for b in found
    ]
    assert [3, 10, 14] == [b.line for b in found]
    assert "out\n" == found[2].code


def test_a_marker_without_a_reason_fails(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("<!-- docs-test: skip -->\n```bash\nls\n```\n")

    with pytest.raises(pytest.fail.Exception, match="a marker reads"):
        blocks(page)


def test_a_marker_without_a_block_fails(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("<!-- docs-test: skip: not a real reason here -->\nsome text\n")

    with pytest.raises(pytest.fail.Exception, match="a marker without a block"):
        blocks(page)


def test_shell_commands_are_split_at_and_and_lines_and_lose_comments() -> None:
    code = 'pip install -e ".[demo]" && rr-actors demo   # the demo\nrr-actors \\\n  demo --fast\n'

    assert [
        ["pip", "install", "-e", ".[demo]"],
        ["rr-actors", "demo"],
        ["rr-actors", "demo", "--fast"],
    ] == list(commands(code))


def test_an_unknown_command_in_an_unmarked_block_fails(tmp_path: Path) -> None:
    block = Block(tmp_path / "p.md", 1, "bash", "make install\n", None)

    with pytest.raises(pytest.fail.Exception, match="not a command this test runs"):
        shell_block(block, tmp_path, set())


def test_openssl_commands_run_in_the_pages_directory(tmp_path: Path) -> None:
    block = Block(tmp_path / "p.md", 1, "bash", "openssl rand -hex -out r.txt 4\n", None)

    shell_block(block, tmp_path, set())

    assert 9 == len((tmp_path / "r.txt").read_text())  # 8 hex digits and a line break


def test_a_system_package_that_ci_does_not_install_fails(tmp_path: Path) -> None:
    installed = Block(tmp_path / "p.md", 1, "bash", "apt-get install -y chromium\n", None)
    other = Block(tmp_path / "p.md", 1, "bash", "apt-get install -y cowsay\n", None)

    shell_block(installed, tmp_path, set())
    with pytest.raises(AssertionError, match=r"does not install \['cowsay'\]"):
        shell_block(other, tmp_path, set())


def test_readme_quickstart_is_examples_quickstart() -> None:
    readme = (ROOT / "README.md").read_text()
    block = readme.split("```python\n", 1)[1].split("```\n", 1)[0]

    assert (ROOT / "examples" / "quickstart.py").read_text() == block


def test_readme_starts_with_the_demo_and_the_test_command_that_ci_runs() -> None:
    lines = (ROOT / "README.md").read_text().splitlines()
    install, test_command = lines[2].rsplit(" && ", 1)

    assert ["```bash", "```"] == [lines[0], lines[3]]
    assert 'pip install -e ".[demo]" && rr-actors demo' == lines[1]
    assert install.endswith('pip install -e ".[dev,bench]"')
    assert ci_test_command() == test_command


def test_no_page_example_or_docstring_cites_a_design_document_the_reader_does_not_have() -> None:
    readable = [*PAGES, *(ROOT / "examples").glob("*.py")]
    readable += [
        p for package in ("rr_actors", "rr_actors_lab") for p in (ROOT / package).rglob("*.py")
    ]
    citing = [rel(path) for path in readable if re.search(r"\bDESIGN\b", path.read_text())]

    assert [] == citing


def test_git_ignores_what_the_demo_writes_by_default() -> None:
    from rr_actors_lab.mission.run import DEFAULT_OUT  # noqa: PLC0415

    ignored = (ROOT / ".gitignore").read_text().splitlines()

    assert f"{DEFAULT_OUT}/" in ignored


def test_a_page_that_leaves_a_registrar_running_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(sys.modules[__name__], "EXIT_TIMEOUT", 2.0)
    page = tmp_path / "page.md"
    page.write_text(
        "```python\nimport rr_actors as rr\nleft = rr.ResourceRegistrar.start('x')\n```\n"
    )
    (block,) = blocks(page)
    kernel = Kernel(tmp_path)
    kernel.run(block, block.code)

    with pytest.raises(pytest.fail.Exception, match="leave something running"):
        kernel.finish(page)


def test_a_python_block_that_reads_input_reads_nothing_and_the_next_block_still_runs(
    tmp_path: Path,
) -> None:
    """A page's `input("press Enter to stop")` (the observer's) ends at once, as with
    `< /dev/null`, and does not eat the page's next block."""
    page = tmp_path / "page.md"
    page.write_text(
        "```python\ntry:\n    input()\nexcept EOFError:\n    ended = True\n```\n\n"
        "```python\nassert ended\n```\n"
    )
    first, second = blocks(page)
    kernel = Kernel(tmp_path)

    kernel.run(first, first.code)
    kernel.run(second, second.code)
    kernel.finish(page)


def test_a_python_block_that_raises_fails_with_the_page_and_line(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("# t\n\n```python\nx = 1\nstart_camera()\n```\n")
    (block,) = blocks(page)
    kernel = Kernel(tmp_path)

    with pytest.raises(pytest.fail.Exception, match=r"(?s)page.md:3 raised.*line 5.*NameError"):
        kernel.run(block, block.code)


def test_the_readme_says_on_which_platforms_it_runs() -> None:
    platform = [
        line for line in (ROOT / "README.md").read_text().splitlines() if "Platform:" in line
    ]

    assert 1 == len(platform)
    assert "Linux" in platform[0]


TUTORIALS = sorted(p.name for p in (ROOT / "docs" / "tutorial").glob("*.md"))
HOW_TOS = sorted(p.name for p in (ROOT / "docs" / "how-to").glob("*.md"))


def first_block(page: Path) -> str:
    match = re.search(r"```bash\n(.*?)```", page.read_text(), re.DOTALL)
    assert match is not None, f"{page} has no bash block"
    return match.group(1)


class TestTheIndex:
    """A newcomer who reads only the README or the docs' index starts the same way and finds
    every tutorial; the index lists every how-to.
    """

    def test_the_docs_index_starts_with_the_readmes_two_commands(self) -> None:
        index = (ROOT / "docs" / "index.md").read_text().splitlines()

        assert index[2] == "```bash"  # right under the title, as in the README
        assert first_block(ROOT / "README.md") == first_block(ROOT / "docs" / "index.md")

    @pytest.mark.parametrize("tutorial", TUTORIALS)
    def test_every_tutorial_is_linked_from_the_index_and_the_readme(self, tutorial: str) -> None:
        index = (ROOT / "docs" / "index.md").read_text()
        where_next = index[index.index("## Where to go next") :]
        readme = (ROOT / "README.md").read_text()

        assert f"(tutorial/{tutorial})" in where_next
        assert f"(docs/tutorial/{tutorial})" in readme

    @pytest.mark.parametrize("how_to", HOW_TOS)
    def test_every_how_to_is_linked_from_the_index(self, how_to: str) -> None:
        index = (ROOT / "docs" / "index.md").read_text()
        where_next = index[index.index("## Where to go next") :]

        assert f"(how-to/{how_to})" in where_next

    def test_the_experiment_tutorial_runs_the_readmes_experiment_command(self) -> None:
        """A reader who follows the tutorial after the README runs what the README runs
        (`--force` was in the README's command only, issue 44 item 7)."""
        command = re.compile(r"^rr-actors experiment \w.*$", re.MULTILINE)
        readme = command.findall((ROOT / "README.md").read_text())
        tutorial = command.findall((ROOT / "docs" / "tutorial" / "first-experiment.md").read_text())

        assert ["rr-actors experiment first --out first-results --force"] == readme
        assert set(readme) <= set(tutorial)

    def test_the_plan_for_the_docs_toolchain_is_in_the_contributors_guide(self) -> None:
        """mkdocs-material's end of life (May 2027): the plan, and why, is recorded where a
        contributor reads (issue 44 item 7; `CONTRIBUTING.md` since issue 54)."""
        guide = (ROOT / "CONTRIBUTING.md").read_text()

        assert "**The plan:" in guide
        assert "May 2027" in guide

    def test_each_time_of_the_second_command_says_when_and_at_which_commit_it_was_measured(
        self,
    ) -> None:
        """The index's table of the README's second command: a time says the day and the
        commit it was measured at, or that it was not measured; `benchmarks/bench_setup.py`
        measures a row (issue 44 items 6 and 8: "(to measure)", and times of a suite a
        third smaller than today's given as today's)."""
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


PAGE = Path(__file__).resolve().parent.parent / "docs" / "reference" / "errors.md"
ERRORS = sorted(
    name
    for name in errors.__all__
    if isinstance(getattr(errors, name), type) and name != "ErrorFrame"
)


def entries() -> dict[str, tuple[str, str]]:
    """Each `**`Name`** (`Base`, ...). Text` entry of the page: name -> (bases, text)."""
    text = PAGE.read_text()
    found = re.findall(r"\*\*`(\w+)`\*\* \(([^)]*)\)\.(.*?)(?=\n\n)", text, re.DOTALL)
    return {name: (bases, body) for name, bases, body in found}


class TestTheErrorsPage:
    """The errors reference is readable in its source: each error with its bases, when it is
    raised and what to do, and not only the directive that renders the docstrings (issue 30).
    """

    @pytest.mark.parametrize("name", ERRORS)
    def test_every_error_has_an_entry_with_its_bases_and_what_to_do(self, name: str) -> None:
        bases, body = entries()[name]

        expected = [b.__name__ for b in getattr(errors, name).__bases__]
        assert expected == re.findall(r"`(\w+)`", bases)
        assert "*What to do:*" in body

    @pytest.mark.parametrize("name", ERRORS)
    def test_every_error_is_importable_from_rr_actors_as_the_page_says(self, name: str) -> None:
        """The page: "importable from `rr_actors.errors`, and also from `rr_actors`".
        `TransferError` and `InternalError` were not (issue 44 item 8); the top's `__all__`
        lists only those a caller catches most (issue 54)."""
        assert getattr(errors, name) is getattr(rr_actors, name, None)

    def test_the_page_draws_every_error_in_its_tree(self) -> None:
        tree = re.search(r"```text\n(.*?)```", PAGE.read_text(), re.DOTALL)

        assert tree is not None
        assert set(ERRORS) <= set(re.findall(r"\b(\w+Error)\b", tree[1]))


# -- the examples a page shows, as files of the built site -------------------------------------

LINK = re.compile(r"\]\((?P<target>[^)\s#]+)(?:#[^)\s]*)?\)")
HREF = re.compile(r'href="(?P<target>[^"#]+)"')


def included_examples(page: Path) -> list[str]:
    """The examples a page shows through a snippet include (their paths in the repository)."""
    return [
        include.group("path")
        for block in blocks(page)
        if (include := SNIPPET.match(block.code.strip())) is not None
        and include.group("path").startswith("examples/")
    ]


SHOWING = [page for page in PAGES[2:] if included_examples(page)]  # (docs/ only)


def test_every_example_a_page_shows_is_linked_by_its_path_in_the_repository() -> None:
    """A page that shows an example (`--8<-- "examples/x.py"`, rendered only in the built
    site) links to its file, relative to the page in the repository, where a reader of
    the page on GitHub or in a checkout finds it (issue 44 item 7)."""
    unlinked = [
        f"{rel(page)}: {example}"
        for page in SHOWING
        for example in included_examples(page)
        if (ROOT / example).resolve()
        not in {
            (page.parent / m.group("target")).resolve() for m in LINK.finditer(page.read_text())
        }
    ]

    assert len(SHOWING) >= 4  # (the walk found the pages)
    assert [] == unlinked


@pytest.mark.timeout(300)
def test_the_built_site_holds_each_example_a_page_links_and_the_link_resolves(
    tmp_path: Path,
) -> None:
    """`mkdocs build --strict`, as CI runs it: each page's link to an example leads, from
    the page's own URL, to the example's file in the site, byte for byte the repository's
    (`docs/hooks/examples.py` copies them and turns the links; issue 44 item 7)."""
    site = tmp_path / "site"
    built = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    assert 0 == built.returncode, built.stderr[-3000:]

    followed: dict[str, set[str]] = {}
    for page in SHOWING:
        source = page.relative_to(ROOT / "docs").with_suffix("")
        html = site / ("index.html" if source.name == "index" else source / "index.html")
        folder = html.parent
        followed[rel(page)] = {
            (folder / href.group("target")).resolve().relative_to(site.resolve()).as_posix()
            for href in HREF.finditer(html.read_text())
            if (folder / href.group("target")).resolve().is_relative_to(site.resolve() / "examples")
        }
        for example in included_examples(page):
            assert example in followed[rel(page)], f"{rel(page)}: no link to {example}"
            assert (ROOT / example).read_bytes() == (site / example).read_bytes()
    assert "examples/filtered_camera.py" in followed["docs/tutorial/first-registrars.md"]


# -- the module reference, generated from the docstrings ---------------------------------------


def modules_script() -> types.ModuleType:
    """`docs/hooks/modules.py`, which writes `docs/reference/modules.md`."""
    spec = importlib.util.spec_from_file_location("docs_modules", ROOT / "docs/hooks/modules.py")
    assert spec is not None
    assert spec.loader is not None
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


def test_the_modules_page_is_what_its_script_writes_from_the_docstrings() -> None:
    """A docstring changed, or a module added or gone, without `python docs/hooks/modules.py`
    run again leaves the reference stale (issue 54)."""
    page = (ROOT / "docs" / "reference" / "modules.md").read_text()

    assert modules_script().render() == page, "run: python docs/hooks/modules.py"


def test_the_modules_page_lists_every_module_with_its_docstrings_first_paragraph() -> None:
    script = modules_script()
    modules = sorted(  # (a file outside a package is data: an exercise's starter)
        p
        for package in ("rr_actors", "rr_actors_lab")
        for p in (ROOT / package).rglob("*.py")
        if "__pycache__" not in p.parts and (p.parent / "__init__.py").is_file()
    )
    rows = [line for line in script.render().splitlines() if line.startswith("| `rr_actors")]
    packages = [p for p in modules if p.name == "__init__.py"]

    assert len(modules) - len(packages) == len(rows)
    assert "modules.md" in (ROOT / "mkdocs.yml").read_text()
    bus = script.first_paragraph(ROOT / "rr_actors" / "_core" / "bus.py")
    assert f"| `rr_actors._core.bus` | {bus} |" in script.render()
    assert "" not in [script.first_paragraph(p) for p in modules]


def test_the_api_page_names_every_top_level_name_in_its_table_in_plain_markdown() -> None:
    """Where a reader first meets the API, before the generated sections: each name of
    `rr.__all__` with one line (issue 54)."""
    page = (ROOT / "docs" / "reference" / "api.md").read_text()
    glance = page[page.index("## The names at a glance") :]
    glance = glance[: glance.index("\n\n", glance.index("|---|"))]

    assert sorted(rr_actors.__all__) == sorted(re.findall(r"^\| `(\w+)` \|", glance, re.M))
    assert page.index("## The names at a glance") < page.index(":::")
