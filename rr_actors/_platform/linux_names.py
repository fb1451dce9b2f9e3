"""Whether a file's names may have changed, told by the kernel (inotify), not by `stat`.

What it buys: a catalog backup's store checks before each commit that its path and its
`-wal` still name the files it opened; one `poll` replaces two `stat` calls, which run
only after something happened.

```
 arm(paths) --inotify_add_watch--> each file: its link count, attributes, a move or
              its deletion (IN_ATTRIB, IN_MOVE_SELF, IN_DELETE_SELF; a rename over it or
              an unlink drops its link count); each directory and symbolic link on the
              way to it (followed and not): a move or deletion
 quiet()   --poll(0) on the process's one inotify descriptor--> events read, each marks
              the watches of its inode "changed" --> quiet: none marked since `arm`
```

It says only that something may have changed (a `chmod` too): the caller `stat`s and arms
again before it checks. It is exact for what it watches (the kernel queues an event before
the causing call returns); a mount over a directory of the path is not watched. One
inotify instance serves the process, its watches refcounted per inode, made with its second
watch: a user has 128 (`fs.inotify.max_user_instances`, for all its programs), so a process
of one store (a process manager's) stats, and a tree holds one per process of several stores
(the supervisor's, a pool's). A forked child makes its own; a parent's watch is never quiet there.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import select
import stat
import struct
import threading
from collections.abc import Sequence
from typing import Any

from rr_actors._platform import forkserver

_IN_ATTRIB = 0x4
_IN_MOVE_SELF = 0x800
_IN_DELETE_SELF = 0x400
_IN_Q_OVERFLOW = 0x4000
_IN_IGNORED = 0x8000
_IN_DONT_FOLLOW = 0x02000000
_IN_MASK_ADD = 0x20000000
_IN_NONBLOCK = os.O_NONBLOCK
_IN_CLOEXEC = os.O_CLOEXEC

_DIRECTORY = _IN_MOVE_SELF | _IN_DELETE_SELF
_FILE = _DIRECTORY | _IN_ATTRIB  # (a directory's link count changes with its subdirectories)
_EVENT = struct.Struct("iIII")  # wd, mask, cookie, len (then len bytes of name)


@functools.cache
def _libc() -> Any:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.inotify_init1.argtypes = [ctypes.c_int]
        libc.inotify_add_watch.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_uint32]
        libc.inotify_rm_watch.argtypes = [ctypes.c_int, ctypes.c_int]
    except (OSError, AttributeError):
        return None
    return libc


class _Instance:
    """The process's inotify descriptor and the watches its watch descriptors serve (any thread,
    `lock`)."""

    def __init__(self, libc: Any, fd: int) -> None:
        self.libc = libc
        self.fd = fd
        self.lock = threading.Lock()
        self.watches: dict[int, set[InotifyNameWatch]] = {}  # wd -> the watches it serves
        self.forked = False  # (set in a forked child: this instance is the parent's)
        self.reading = False  # while a thread reads and hands events out (`quiet` waits then)

    def add(self, watch: InotifyNameWatch, path: bytes, mask: int) -> int | None:
        """Watch `path` for `watch` (under `lock`); `None` if it cannot be watched."""
        wd = self.libc.inotify_add_watch(self.fd, path, mask | _IN_MASK_ADD)
        if wd < 0:
            return None
        self.watches.setdefault(wd, set()).add(watch)
        return int(wd)

    def remove(self, watch: InotifyNameWatch, wd: int) -> None:
        """`watch` no longer needs `wd` (under `lock`); the last one removes it."""
        served = self.watches.get(wd)
        if served is None:
            return
        served.discard(watch)
        if not served:
            del self.watches[wd]
            self.libc.inotify_rm_watch(self.fd, wd)  # (an error: the kernel removed it)

    def drain(self) -> None:
        """Read every queued event; mark the watches they concern (under `lock`)."""
        self.reading = True
        try:
            self._drain()
        finally:
            self.reading = False

    def _drain(self) -> None:
        while True:
            try:
                data = os.read(self.fd, 65536)
            except BlockingIOError:
                return
            except OSError:  # (cannot tell: every watch checks with stat)
                data = b""
            if not data:
                self._mark_all()
                return
            offset = 0
            while offset + _EVENT.size <= len(data):
                wd, mask, _, length = _EVENT.unpack_from(data, offset)
                offset += _EVENT.size + length
                if mask & _IN_Q_OVERFLOW:  # events were lost: any name may have changed
                    self._mark_all()
                    continue
                served = self.watches.get(wd, ())
                for watch in served:
                    watch.changed = True
                if mask & _IN_IGNORED:  # the kernel removed the watch (its inode is gone)
                    self.watches.pop(wd, None)

    def _mark_all(self) -> None:
        for served in self.watches.values():
            for watch in served:
                watch.changed = True


_instance: _Instance | None = None
_instance_lock = threading.Lock()
_made = 0  # watches made in this process: its instance waits for the second


def _forget_in_child() -> None:
    global _instance, _instance_lock, _made
    _instance_lock = threading.Lock()  # (a thread of the parent may have held it)
    _made, InotifyNameWatch.armable = 0, False
    if _instance is not None:
        _instance.forked = True
        with contextlib.suppress(OSError):
            os.close(_instance.fd)
        _instance = None


forkserver.after_fork_in_child("the inotify instance", _forget_in_child)


class InotifyNameWatch:
    """Tells whether the names it was armed with may have changed (one thread at a time)."""

    armable = False  # (the process's instance is made: every watch of the process, at once)

    def __init__(self) -> None:
        self._instance: _Instance | None = None  # (the process's, at the first `arm` after)
        # its own: one poll object polled by two threads at once raises RuntimeError
        self._poll = select.poll()
        self._wds: list[int] = []
        self.changed = True  # (not armed yet)

    def arm(self, paths: Sequence[str]) -> bool:
        """Watch `paths` (absolute paths of existing files) instead of what was watched before;
        whether every one is watched (if not, it is never quiet until an `arm` that succeeds).
        """
        if self._instance is None and _instance is not None:
            self._instance = _instance
            self._poll.register(_instance.fd, select.POLLIN)
        instance = self._instance
        if instance is None:  # (the process's one watch: the caller stats)
            return False
        with instance.lock:
            self._forget(instance)
            if instance.forked:
                return False
            targets, watched = _targets(paths)
            for target, mask in targets:
                wd = instance.add(self, target, mask)
                if wd is None:
                    watched = False
                else:
                    self._wds.append(wd)
            self.changed = not watched
            return watched

    def quiet(self) -> bool:
        """Whether nothing happened to the names armed since `arm`."""
        instance = self._instance
        if instance is None or instance.forked:  # (forked: its descriptor is closed here)
            return False
        # nothing queued and no thread handing events out (`reading`): none concerns this one
        if self._poll.poll(0) or instance.reading:
            with instance.lock:
                instance.drain()
        return not self.changed

    def close(self) -> None:
        if self._instance is not None:
            with self._instance.lock:
                self._forget(self._instance)
        self.changed = True

    def _forget(self, instance: _Instance) -> None:
        if not instance.forked:
            for wd in self._wds:
                instance.remove(self, wd)
        self._wds = []


def _targets(paths: Sequence[str]) -> tuple[list[tuple[bytes, int]], bool]:
    """What to watch for `paths`: each file, and each directory and symbolic link on the way;
    and whether every one exists.
    """
    targets: dict[tuple[bytes, int], None] = {}
    complete = True
    for path in paths:
        parts = path.split(os.sep)
        for end in range(2, len(parts) + 1):  # (not the root: it cannot move)
            prefix = os.sep.join(parts[:end])
            name = os.fsencode(prefix)
            try:
                own = os.lstat(prefix).st_mode
                pointed = os.stat(prefix).st_mode
            except OSError:
                complete = False
                continue
            targets[(name, (_DIRECTORY if stat.S_ISDIR(own) else _FILE) | _IN_DONT_FOLLOW)] = None
            if stat.S_ISLNK(own):
                targets[(name, _DIRECTORY if stat.S_ISDIR(pointed) else _FILE)] = None
    return list(targets), complete


def watch_names() -> InotifyNameWatch | None:
    """A new watch, not armed yet (nor armable while it is the process's one: the caller
    stats); `None` where inotify is missing. The second makes the process's instance."""
    global _instance, _made
    if _libc() is None:
        return None
    with _instance_lock:
        _made += 1
        if _instance is None and _made > 1:  # (refused: the next watch asks again)
            fd = _libc().inotify_init1(_IN_NONBLOCK | _IN_CLOEXEC)
            _instance = _Instance(_libc(), fd) if fd >= 0 else None
            InotifyNameWatch.armable = _instance is not None
    return InotifyNameWatch()
