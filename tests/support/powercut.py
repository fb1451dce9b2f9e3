"""A disk that records every write and flush, to replay a power cut at each flush (root).

This machine's kernel has no device-mapper (no `dm-log-writes`, no `dm-flakey`) but has
FUSE and loop devices: the same record is made one layer up. A loop device's flush is an
`fsync` of its backing file, so a backing file served by a FUSE daemon of ours sees the
block device's writes and flushes in order, as `dm-log-writes` would log them:

```
 ext4 --bio--> /dev/loopN --write / fsync of its file--> FUSE --> LoggingDisk (this
   module run as a program: `python -m tests.support.powercut MOUNTPOINT SIZE`)
   log: ("w", offset, bytes), ("f",) at each flush, ("m", label) at each mark
 flush_points(log) --> the disk as a power cut after each flush may leave it: every
   write logged before that flush, none after; with the marks logged before the next
```

A flush covers the writes that completed before it was sent; the daemon answers a write
only once it is logged, so what the log holds before a flush is a state the disk may be
in after a power cut from that flush until the next one (a disk that kept nothing
unflushed: the worst case). Marks come from the test (`Disk.mark`), each logged before
`mark` returns: what was acknowledged before a mark must be there in every such state
whose cut may come after it.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import pickle
import select
import shutil
import struct
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, ClassVar

Entry = tuple[Any, ...]

# -- the FUSE daemon (linux/fuse.h, protocol 7.x) ----------------------------------------

_IN = struct.Struct("<IIQQIIIHH")  # len, opcode, unique, nodeid, uid, gid, pid, extlen, pad
_OUT = struct.Struct("<IiQ")  # len, error, unique
_ATTR = struct.Struct("<QQQQQQIIIIIIIIII")  # fuse_attr (88 bytes)
_INIT_OUT = struct.Struct("<IIIIHHIIHHII24x")  # fuse_init_out (64 bytes)
_RW_IN = struct.Struct("<QQIIQII")  # fuse_read_in / fuse_write_in (40 bytes)
LOOKUP, FORGET, GETATTR, SETATTR = 1, 2, 3, 4
OPEN, READ, WRITE, STATFS, RELEASE, FSYNC = 14, 15, 16, 17, 18, 20
FLUSH, INIT, OPENDIR, RELEASEDIR, ACCESS = 25, 26, 27, 29, 34
INTERRUPT, DESTROY, BATCH_FORGET = 36, 38, 42
_NO_REPLY = {FORGET, INTERRUPT, BATCH_FORGET}
FILE_NAME = "disk"
_ROOT, _FILE = 1, 2
_MAX_WRITE = 128 * 1024
_DIRECT_IO = 1  # FOPEN_DIRECT_IO: no page cache between the loop device and the log


class LoggingDisk:
    """The FUSE file system of one file, `disk`, of `size` bytes (zeros at first)."""

    def __init__(self, size: int) -> None:
        self.data = bytearray(size)
        self.log: list[Entry] = []
        self.fd = -1

    def mount(self, mountpoint: str) -> None:
        self.fd = os.open("/dev/fuse", os.O_RDWR)
        options = f"fd={self.fd},rootmode=40000,user_id=0,group_id=0".encode()
        libc = ctypes.CDLL(None, use_errno=True)
        flags = 2 | 4  # MS_NOSUID | MS_NODEV
        if libc.mount(b"rr-powercut", mountpoint.encode(), b"fuse", flags, options) != 0:
            code = ctypes.get_errno()
            raise OSError(code, f"mount fuse at {mountpoint}: {os.strerror(code)}")

    def attr(self, node: int) -> bytes:
        if node == _ROOT:
            return _ATTR.pack(_ROOT, 0, 0, 0, 0, 0, 0, 0, 0, 0o40755, 2, 0, 0, 0, 4096, 0)
        size = len(self.data)
        return _ATTR.pack(_FILE, size, size // 512, 0, 0, 0, 0, 0, 0, 0o100600, 1, 0, 0, 0, 4096, 0)

    def handle(self, opcode: int, node: int, body: bytes) -> tuple[int, bytes]:
        """The answer (an errno, its bytes) to one request."""
        if opcode in (FLUSH, RELEASE, RELEASEDIR, ACCESS, DESTROY):
            return 0, b""
        step = self._STEPS.get(opcode)
        return (errno.ENOSYS, b"") if step is None else step(self, node, body)

    def _init(self, _node: int, body: bytes) -> tuple[int, bytes]:
        _, minor, readahead, _ = struct.unpack_from("<IIII", body)
        return 0, _INIT_OUT.pack(7, min(minor, 31), readahead, 0, 16, 12, _MAX_WRITE, 1, 0, 0, 0, 0)

    def _lookup(self, _node: int, body: bytes) -> tuple[int, bytes]:
        if body.split(b"\0", 1)[0] != FILE_NAME.encode():
            return errno.ENOENT, b""
        return 0, struct.pack("<QQQQII", _FILE, 0, 3600, 3600, 0, 0) + self.attr(_FILE)

    def _getattr(self, node: int, _body: bytes) -> tuple[int, bytes]:
        return 0, struct.pack("<QII", 3600, 0, 0) + self.attr(node)

    def _open(self, node: int, _body: bytes) -> tuple[int, bytes]:
        return 0, struct.pack("<QII", 1, _DIRECT_IO if node == _FILE else 0, 0)

    def _read(self, _node: int, body: bytes) -> tuple[int, bytes]:
        _, offset, size, *_ = _RW_IN.unpack_from(body)
        return 0, bytes(self.data[offset : offset + size])

    def _write(self, _node: int, body: bytes) -> tuple[int, bytes]:
        _, offset, size, *_ = _RW_IN.unpack_from(body)
        data = body[_RW_IN.size : _RW_IN.size + size]
        self.data[offset : offset + len(data)] = data
        self.log.append(("w", offset, data))
        return 0, struct.pack("<II", len(data), 0)

    def _fsync(self, _node: int, _body: bytes) -> tuple[int, bytes]:
        self.log.append(("f",))
        return 0, b""

    def _statfs(self, _node: int, _body: bytes) -> tuple[int, bytes]:
        blocks = len(self.data) // 4096
        return 0, struct.pack("<QQQQQIII28x", blocks, 0, 0, 2, 0, 4096, 255, 4096)

    _STEPS: ClassVar[dict[int, Callable[[LoggingDisk, int, bytes], tuple[int, bytes]]]] = {
        INIT: _init,
        LOOKUP: _lookup,
        GETATTR: _getattr,
        SETATTR: _getattr,
        OPEN: _open,
        OPENDIR: _open,
        READ: _read,
        WRITE: _write,
        FSYNC: _fsync,
        STATFS: _statfs,
    }

    def serve_one(self) -> bool:
        """Answer one request; `False` once the file system is unmounted."""
        try:
            request = os.read(self.fd, _MAX_WRITE + 64 * 1024)
        except OSError as exc:
            if exc.errno == errno.ENODEV:
                return False
            if exc.errno in (errno.EINTR, errno.ENOENT):  # (an interrupted request)
                return True
            raise
        header = _IN.unpack_from(request)
        opcode, unique, node = int(header[1]), int(header[2]), int(header[3])
        if opcode in _NO_REPLY:
            return True
        code, reply = self.handle(opcode, node, request[_IN.size :])
        with contextlib.suppress(FileNotFoundError):  # (its caller gave up: ENOENT)
            os.write(self.fd, _OUT.pack(_OUT.size + len(reply), -code, unique) + reply)
        return opcode != DESTROY


def answer(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def serve(mountpoint: str, size: int) -> None:
    """The daemon's program: mount, then answer FUSE requests and the test's commands on
    stdin (`mark LABEL`, `dump PATH`), each answered `ok` on stdout once done."""
    disk = LoggingDisk(size)
    disk.mount(mountpoint)
    answer("ok")
    commands = sys.stdin.fileno()
    while True:
        ready, _, _ = select.select([disk.fd, commands], [], [])
        if commands in ready:
            line = sys.stdin.readline().split(maxsplit=1)
            if not line:
                return
            if line[0] == "mark":
                disk.log.append(("m", line[1].strip()))
            elif line[0] == "dump":
                Path(line[1].strip()).write_bytes(pickle.dumps(disk.log))
            answer("ok")
        if disk.fd in ready and not disk.serve_one():
            return


# -- the test's side ------------------------------------------------------------------------


def run(*command: str) -> str:
    return subprocess.run(command, check=True, capture_output=True, text=True, timeout=120).stdout


def unmount(where: Path) -> None:
    """Unmount `where`; if it is busy, detach it lazily (never left mounted) and raise."""
    try:
        run("umount", str(where))
    except subprocess.CalledProcessError:
        run("umount", "--lazy", str(where))
        raise


class Disk:
    """A logged disk with ext4 on it, mounted at `mounted` (see `logged_disk`)."""

    def __init__(self, daemon: subprocess.Popen[str], mounted: Path, size: int) -> None:
        self._daemon = daemon
        self.mounted = mounted
        self.size = size

    def _ask(self, command: str) -> None:
        assert self._daemon.stdin is not None
        assert self._daemon.stdout is not None
        self._daemon.stdin.write(command + "\n")
        self._daemon.stdin.flush()
        answer = self._daemon.stdout.readline().strip()
        if answer != "ok":
            raise RuntimeError(f"the logging disk answered {answer!r} to {command!r}")

    def mark(self, label: str) -> None:
        """Log `label` after every write and flush logged so far (returns once logged)."""
        self._ask(f"mark {label}")

    def dump(self, path: Path) -> list[Entry]:
        self._ask(f"dump {path}")
        log: list[Entry] = pickle.loads(path.read_bytes())
        return log


@contextlib.contextmanager
def logged_disk(work: Path, size: int = 32 * 1024 * 1024) -> Iterator[Disk]:
    """A FUSE-backed loop device with a fresh ext4 on it, mounted under `work` (root)."""
    fuse_dir, mounted = work / "fuse", work / "ext4"
    fuse_dir.mkdir()
    mounted.mkdir()
    command = [sys.executable, "-m", "tests.support.powercut", str(fuse_dir), str(size)]
    daemon = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    loop = None
    try:
        assert daemon.stdout is not None
        if daemon.stdout.readline().strip() != "ok":
            raise RuntimeError("the logging disk's daemon did not start")
        loop = run("losetup", "--find", "--show", str(fuse_dir / FILE_NAME)).strip()
        run("mkfs.ext4", "-q", "-E", "nodiscard", loop)  # (the daemon has no discard)
        run("mount", "-t", "ext4", loop, str(mounted))
        try:
            yield Disk(daemon, mounted, size)
        finally:
            unmount(mounted)
    finally:
        if loop is not None:
            run("losetup", "--detach", loop)
        with contextlib.suppress(subprocess.CalledProcessError):  # (not mounted: no daemon)
            unmount(fuse_dir)
        for pipe in (daemon.stdin, daemon.stdout):
            if pipe is not None:
                pipe.close()
        daemon.wait(30)


def flush_points(log: list[Entry], size: int, after: str) -> Iterator[tuple[int, bytes, set[str]]]:
    """Each power cut that leaves the disk as of a flush: its index in the log, the disk
    then (every write logged before that flush, none after), and every mark logged before
    the next flush (or the log's end): a cut anywhere up to that next flush may leave just
    that disk. From the last flush before mark `after` on."""
    data = bytearray(size)
    marks: set[str] = set()
    point: tuple[int, bytes] | None = None  # the last flush: (index, the disk then)
    for index, entry in enumerate(log):
        if entry[0] == "w":
            data[entry[1] : entry[1] + len(entry[2])] = entry[2]
        elif entry[0] == "m":
            marks.add(entry[1])
        else:
            if point is not None and after in marks:
                yield point[0], point[1], set(marks)
            point = (index, bytes(data))
    if point is not None and after in marks:
        yield point[0], point[1], set(marks)


@contextlib.contextmanager
def mounted_image(data: bytes) -> Iterator[Path]:
    """`data` as a file system mounted read-write on a scratch copy in memory
    (/dev/shm): ext4 replays its journal there as after a real power cut."""
    scratch = Path(tempfile.mkdtemp(prefix="rr-powercut-", dir="/dev/shm"))
    image, mounted = scratch / "image", scratch / "mnt"
    mounted.mkdir()
    image.write_bytes(data)
    loop = run("losetup", "--find", "--show", str(image)).strip()
    try:
        run("mount", "-t", "ext4", loop, str(mounted))
        try:
            yield mounted
        finally:
            unmount(mounted)
    finally:
        run("losetup", "--detach", loop)
        shutil.rmtree(scratch)


if __name__ == "__main__":
    serve(sys.argv[1], int(sys.argv[2]))
