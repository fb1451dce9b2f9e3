"""Who else can read or change a private file or directory, and who this process runs as.

One check for a host's key (`ZenohTLS` warns) and the CA's key and directory (`rr-actors
certs` refuses): a private file is this user's, mode `0600` or less; a private directory
is this user's and writable by nobody else.
"""

from __future__ import annotations

import os
import stat

_GROUP_OTHERS = 0o077  # every permission bit of group and others
_GROUP_OTHERS_READ = 0o044
_GROUP_OTHERS_WRITE = 0o022


def _euid() -> int | None:
    geteuid = getattr(os, "geteuid", None)  # POSIX only
    return None if geteuid is None else int(geteuid())


def _name(uid: int) -> str | None:
    try:
        import pwd  # noqa: PLC0415 - POSIX only
    except ImportError:
        return None
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:  # a uid without an entry in the user database
        return None


def user(uid: int | None = None) -> str:
    """`uid` (default: this process's effective user) as `name (uid N)`, or `uid N`."""
    uid = _euid() if uid is None else uid
    if uid is None:
        return "this user"
    name = _name(uid)
    return f"uid {uid}" if name is None else f"{name} (uid {uid})"


def _foreign(st: os.stat_result) -> str | None:
    me = _euid()
    if me is None or st.st_uid == me:
        return None
    return f"is owned by {user(st.st_uid)}, not by this user, {user(me)}"


def private_file_trouble(path: str | os.PathLike[str]) -> str | None:
    """Why the file `path` (a key) is not private, with the fix; `None` if it is (OSError)."""
    st = os.stat(path)
    foreign = _foreign(st)
    if foreign is not None:
        me = _euid()
        assert me is not None  # else nobody is foreign
        return f"{foreign}: chown {_name(me) or me} {os.fspath(path)}"
    mode = stat.S_IMODE(st.st_mode)
    if mode & _GROUP_OTHERS:
        kind = "readable" if mode & _GROUP_OTHERS_READ else "writable"
        return f"is {kind} by group or others (mode {mode:04o}): chmod 600 {os.fspath(path)}"
    return None


def private_dir_trouble(path: str | os.PathLike[str]) -> str | None:
    """Why the directory `path` is not private, with the fix; `None` if it is."""
    st = os.stat(path)
    foreign = _foreign(st)
    if foreign is not None:
        return f"{foreign} (use a directory of your own)"
    mode = stat.S_IMODE(st.st_mode)
    if mode & _GROUP_OTHERS_WRITE:
        return (
            f"is writable by group or others (mode {mode:04o}): they can put, rename or "
            f"replace files in it (chmod 700 {os.fspath(path)}, or use a directory of your own)"
        )
    return None
