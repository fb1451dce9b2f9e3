"""Real small file systems for the store's tests: a tmpfs of a few hundred KiB that a test
fills up (a full disk, `ENOSPC`) or remounts read-only.

Mounting needs root (CI runs as root); elsewhere `mounted` skips the test.
"""

from __future__ import annotations

import contextlib
import errno
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest


def _run(*command: str) -> None:
    subprocess.run(command, check=True, capture_output=True, text=True)


@contextlib.contextmanager
def mounted(where: Path, size: str = "1m") -> Iterator[Path]:
    """A new tmpfs of `size` bytes at `where` (created), unmounted when the block ends.

    Skips the test when this process cannot mount (not root).
    """
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root (CI runs as root)")
    where.mkdir()
    _run("mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(where))
    try:
        yield where
    finally:
        try:
            _run("umount", str(where))
        except subprocess.CalledProcessError:
            _run("umount", "--lazy", str(where))  # never leave it mounted; still fail
            raise


def remount_read_only(where: Path) -> None:
    """Make the tmpfs at `where` read-only: writes fail with `EROFS`, even as root."""
    _run("mount", "-o", "remount,ro", str(where))


def fill(where: Path) -> Path:
    """Fill the file system of `where` with a file of zeros until `ENOSPC`; return it."""
    filler = where / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    block = bytes(4096)
    try:
        while True:
            os.write(fd, block)
    except OSError as exc:
        if exc.errno != errno.ENOSPC:
            raise
    finally:
        os.close(fd)
    return filler
