"""What the AF_UNIX carrier's listener and channels need of their process's membership.

Rule 19 on the AF_UNIX carrier (`system.py`). Each listener publishes, next to its
`.limit` file, `<name>.restart` (`Rendezvous.restart_path`): `0` when nobody restarts the
registrar, else the pid (and start time) of the process that speaks for it when it
dies: the supervisor's process of a manager process (`_process/child.py` says so with
`AttachedSystem.supervised_by`; that process restarts it, or sends the death watch if it
gives up or owns an unsupervised `RemoteRegistrar`), or its own process while
`DIRECTORY.restart_expected(name)` (a thread manager: it dies with that process). A
process *judges* a registrar of another process when its connection to it ends or a
connect to it fails: a tombstone says stopped (nothing to do); a process that holds
the name's lock serves it (after a grace of `ENDING_GRACE` s, for a process still
exiting); otherwise, with no speaker or a speaker gone (or a zombie), every endpoint
served in this process gets `peer_lost(name)` once (until the name is served again);
with a living speaker, the name is *awaited*: polled every `AWAIT_POLL` s until it is
served again (then this process, if it serves an endpoint, connects to it at once, so
that its next death is seen too), stopped, or its speaker is gone too (then lost). The
speaker's own process judges nothing of what it speaks for: it decides itself. Limits:

- a process hears it only if it has, or tries, a connection to that registrar: one that
  holds ids there has one (its calls opened it; it lasts until the peer ends), so the
  gap is a consumer whose connection ended earlier for another reason and that sends
  nothing: it hears at its next message (the failed connect is judged);
- the lock probe is a shared `flock` held for microseconds; a listener taking the name
  meanwhile retries for `LOCK_RETRY` s before it reports `DuplicateNameError`;
- a pid is trusted with its start time where `/proc` has it; elsewhere a pid reused
  by an unrelated process keeps a registrar awaited (not lost) until that one ends;
- what a speaker that lives on does with the name (a restart, or the death watch when
  it gives up) is its own: the carrier waits only for its death;
- `DIRECTORY.restart_expected(name)` is read when the registrar starts serving.
"""

from __future__ import annotations

from typing import Protocol

__all__ = ["Member", "Rendezvous"]


class Rendezvous(Protocol):
    """Where a carrier that meets in a directory finds a registrar (the `unix` carrier).

    What its listener (`inbound.py`) and its peers (`outbound.py`) need of the system's
    address: the paths of one registrar's files and the system's secret.
    """

    @property
    def authkey(self) -> bytes:
        """The system's secret; a connection that cannot prove it is refused."""
        ...

    def socket_path(self, name: str) -> str:
        """The path registrar `name` listens on."""
        ...

    def tombstone_path(self, name: str) -> str:
        """A file that says registrar `name` was stopped cleanly (not crashed)."""
        ...

    def lock_path(self, name: str) -> str:
        """The file whose lock the process serving registrar `name` holds."""
        ...

    def limit_path(self, name: str) -> str:
        """A file that holds registrar `name`'s `max_message_bytes`, for senders."""
        ...

    def restart_path(self, name: str) -> str:
        """A file that says who speaks for registrar `name` if its process dies (rule 19):
        `0` for nobody, else that process's pid and start time."""
        ...


class Member(Protocol):
    """A process's membership as a carrier's channels see it: its rendezvous, closed or not."""

    @property
    def address(self) -> Rendezvous:
        """Where registrars of the system are found."""
        ...

    @property
    def closed(self) -> bool:
        """Whether this process left the system (no new channel is opened then)."""
        ...

    def supervisor(self, name: str) -> str:
        """What registrar `name`, served here, publishes in its `restart_path` file."""
        ...

    def peer_ended(self, name: str) -> None:
        """The connection to registrar `name` of another process ended, or a connect to it
        failed: find out (on another thread) whether it is lost (rule 19). Returns at once."""
        ...
