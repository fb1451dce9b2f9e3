"""A virtual environment with rr_actors and its two dependencies only: no extra at all.

As a new user's after `pip install -e .` (no extra named): `pykka` and `cloudpickle`
installed by pip from the package index (at the versions this interpreter has, so pip's
cache serves them), and this checkout on `sys.path` through a `.pth` file (what an
editable install adds; the checkout itself is not touched, so tests that build wheels
from it beside this one are not disturbed). `--system-site-packages` is off: nothing of
this interpreter's site-packages (the dev extra) is seen. Made once per test session.
"""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent.parent

CORE = ("pykka", "cloudpickle")
"""The runtime's dependencies (`pyproject.toml`'s `dependencies`)."""


def make_bare_venv(where: Path) -> Path:
    """Make the environment in `where`; return its `python`."""
    venv.EnvBuilder(with_pip=False, system_site_packages=False).create(where)
    python = where / "bin" / "python"
    pins = [f"{name}=={importlib.metadata.version(name)}" for name in CORE]
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            str(python),
            "install",
            "--quiet",
            "--no-deps",
            "--disable-pip-version-check",
            *pins,
        ],
        check=True,
        capture_output=True,
        timeout=300,
    )
    purelib = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True,
        capture_output=True,
        text=True,
        timeout=60,
    ).stdout.strip()
    (Path(purelib) / "rr_actors_checkout.pth").write_text(f"{ROOT}\n")
    assert sysconfig.get_paths()["purelib"] != purelib  # (not this interpreter's)
    return python
