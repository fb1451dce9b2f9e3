"""Two hosts on one machine: Linux network namespaces joined by a veth pair, and workers in them.

Used by the multi-host tests (`tests/multihost/`) and `benchmarks/bench_zenoh.py`. Needs root
(`ip netns`); `require_root()` says so in one sentence.

    test process                                namespace rrh-<pid>-<n>-a   namespace ...-b
    ------------                                -------------------------   ---------------
    TwoHosts() --ip netns add, ip link add-->   rr0 10.77.<n>.1/24 <-veth-> rr0 10.77.<n>.2/24
    TwoHosts(outsider=True) also -->           rr1 10.78.<n>.1/24 <-veth-> rr1 10.78.<n>.3/24
                                                                     in namespace ...-c
    host.spawn() --ip netns exec NS python-->   Worker (python -c "from tests.support import hosts")
      a socket path in a 0700 directory   <--AF_UNIX, authkey--  Client(path)
      host.call(fn, *args) --cloudpickle(fn, args)-->  runs fn(*args) on a thread of its own
                           <--(call id, ok, cloudpickle(result or exception))--

Why these choices:

- AF_UNIX path sockets live in the file system, not in a network namespace, so the test process
  drives every worker over one per-worker socket whatever namespace the worker is in; only the
  traffic under test crosses the veth. The authkey goes to the worker on its stdin (not argv,
  which `ps` shows).
- A worker is a fresh interpreter (`ip netns exec` execs it in place: its pid is the worker's),
  never a fork: a process that has opened a Zenoh session must not fork.
- A worker never outlives the test process: it asks for SIGKILL when its parent dies
  (`PR_SET_PDEATHSIG`, then checks the parent is still the one that started it, closing the
  race), and it exits when its stdin or its connection reaches end of file. (The death signal
  follows the *thread* that started the worker: start workers from the test's main thread.)
- Namespace names carry the test process's pid, so parallel runs on one machine never clash; a
  run killed before its cleanup leaves namespaces whose pid is dead, and the next run deletes
  them (`sweep_stale()`). The veth pair is created directly inside the two namespaces, so
  nothing ever appears in the machine's own namespace and its names cannot clash.
- The outsider `c` (an attacker, say) reaches `a` on a veth of its own, routed to all
  of `a`'s addresses: cutting the link between `a` and `b` (`link_down`) leaves it.
- No sleeps: `call` waits on the worker's reply with a bound; a worker's readiness is its
  connection (accepted with a bound, watching the worker's pidfd so a worker that died at
  start fails at once with its output).

Functions sent with `call`, and their arguments, are cloudpickled; those of test modules and
benchmarks are sent by value (every such module is registered with cloudpickle), those of this
module by reference, so a function can keep state in the worker between calls in `KEPT` (this
module's dict, in the worker's own copy of this module).
"""

from __future__ import annotations

import contextlib
import ctypes
import itertools
import json
import os
import queue
import selectors
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from concurrent.futures import wait as futures_wait
from multiprocessing.connection import Client, Connection, answer_challenge, deliver_challenge
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import cloudpickle

ROOT = Path(__file__).resolve().parents[2]
TESTS = ROOT / "tests"

WORKER_MAIN = "from tests.support import hosts; hosts._worker_main()"
"""What a worker runs (the repository is on its PYTHONPATH, so `tests` is a package there)."""

PREFIX = "rrh"
"""Namespace names are `rrh-<pid>-<n>-a` and `-b`."""

INTERFACE = "rr0"
"""The veth end's name inside each namespace."""

OUTSIDE = "rr1"
"""The name of the outsider's veth ends (in `c` and `a`)."""

START_TIMEOUT = 30.0
"""Seconds a worker gets to start and connect (a loaded CI machine starts Python slowly)."""

STOP_TIMEOUT = 5.0
"""Seconds a worker gets to exit after it was told to stop, before it is SIGKILLed."""

KEPT: dict[str, Any] = {}
"""State a worker's functions keep between calls (in the worker: its own copy of this dict)."""

T = TypeVar("T")

_PR_SET_PDEATHSIG = 1
_numbers = itertools.count()


class WorkerDiedError(RuntimeError):
    """A worker's process ended while a call to it was waiting (or before it connected)."""


class RemoteTraceback(Exception):  # noqa: N818 (named as concurrent.futures names it)
    """The worker-side traceback of an exception `call` re-raises (its `__cause__`)."""

    def __str__(self) -> str:
        return "\n" + str(self.args[0])


def require_root() -> str | None:
    """Why the multi-host machinery cannot run here (not root), or `None` if it can.

    Only a missing root is a reason to skip: CI runs as root, so there these tests always
    run. Root without `ip` (iproute2) fails when the hosts are made, naming the package.
    """
    if os.geteuid() != 0:
        return "needs root: two network namespaces joined by a veth pair (`ip netns`)"
    return None


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)  # noqa: S607
    if done.returncode != 0:
        raise RuntimeError(f"`ip {' '.join(args)}` failed: {done.stderr.strip()}")


def namespaces() -> list[str]:
    """The names of the machine's named network namespaces (`ip netns list`)."""
    done = subprocess.run(
        ["ip", "-json", "netns", "list"],  # noqa: S607
        capture_output=True,
        text=True,
        check=True,
    )
    return [entry["name"] for entry in json.loads(done.stdout or "[]")]


def ours(pid: int | None = None) -> list[str]:
    """The namespaces made by the process `pid` (default: this one)."""
    mark = f"{PREFIX}-{os.getpid() if pid is None else pid}-"
    return [name for name in namespaces() if name.startswith(mark)]


def sweep_stale() -> list[str]:
    """Delete namespaces left by runs whose process is gone; return their names."""
    swept = []
    for name in namespaces():
        parts = name.split("-")
        if len(parts) != 4 or parts[0] != PREFIX or not parts[1].isdigit():
            continue
        if not Path(f"/proc/{parts[1]}").exists():
            with contextlib.suppress(RuntimeError):
                _ip("netns", "del", name)
                swept.append(name)
    return swept


# -- the worker's side -------------------------------------------------------------------------


def _worker_main() -> None:  # pragma: no cover (runs in the worker)
    """Connect back, then run each call on its own thread until told to stop (or orphaned)."""
    hello = json.loads(sys.stdin.readline())
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != hello["parent"]:
        os._exit(3)  # the test process died before the death signal was armed
    threading.Thread(target=_exit_at_eof, name="stdin-watch", daemon=True).start()
    conn = Client(hello["address"], family="AF_UNIX", authkey=bytes.fromhex(hello["authkey"]))
    send_lock = threading.Lock()

    def run(call_id: int, payload: bytes) -> None:
        try:
            fn, args, kwargs = cloudpickle.loads(payload)
            reply = (call_id, True, cloudpickle.dumps(fn(*args, **kwargs)))
        except BaseException as exc:
            text = traceback.format_exc()
            try:
                reply = (call_id, False, cloudpickle.dumps((exc, text)))
            except Exception:
                reply = (call_id, False, cloudpickle.dumps((RuntimeError(repr(exc)), text)))
        with send_lock, contextlib.suppress(OSError):
            conn.send(reply)

    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            break
        if message is None:
            break
        threading.Thread(target=run, args=message, daemon=True).start()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)  # no interpreter teardown: native threads (Zenoh's) may not let it finish


def _exit_at_eof() -> None:  # pragma: no cover (runs in the worker)
    sys.stdin.read()
    os._exit(0)


# -- the test's side ---------------------------------------------------------------------------


_BY_VALUE_LOCK = threading.Lock()
"""Held while test modules are registered to be sent by value (one pickling at a time)."""


def _dumps_by_value(obj: Any) -> bytes:
    """`cloudpickle.dumps(obj)` with test and benchmark modules sent by value (workers
    cannot import them by name), registered for this pickling only: other tests of the
    session pickle the same modules by reference (by value, a module's globals such as
    locks would travel too)."""
    with _BY_VALUE_LOCK:
        registered = []
        for name, module in list(sys.modules.items()):
            path = getattr(module, "__file__", None)
            # (not a package: cloudpickle sends every module under a registered package by
            # value, this one too, whose state a worker must share with its main loop)
            if name in {__name__, "__main__"} or not path or hasattr(module, "__path__"):
                continue
            where = Path(path)
            if where.is_relative_to(TESTS) or where.is_relative_to(ROOT / "benchmarks"):
                cloudpickle.register_pickle_by_value(module)
                registered.append(module)
        try:
            return cloudpickle.dumps(obj)
        finally:
            for module in registered:
                cloudpickle.unregister_pickle_by_value(module)


class Worker:
    """A Python process inside a host's namespace that runs the functions it is sent.

    Attributes:
        host: the host it runs on.
        pid: its process id (a child of the test process).
        log: the file that collects its stdout and stderr.
    """

    def __init__(self, host: Host, directory: Path, number: int) -> None:
        self.host = host
        self.log = directory / f"{host.name}-{number}.log"
        path = str(directory / f"{host.name}-{number}.sock")
        authkey = os.urandom(32)
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        listener.bind(path)
        listener.listen(1)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *_pythonpath()])}
        inside = ["ip", "netns", "exec", host.namespace] if host.namespace else []
        with self.log.open("wb") as log:
            self.process = subprocess.Popen(
                [
                    *inside,
                    sys.executable,
                    "-c",
                    "from tests.support import hosts; hosts._worker_main()",
                ],
                stdin=subprocess.PIPE,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
                cwd=ROOT,
            )
        self.pid = self.process.pid
        assert self.process.stdin is not None
        hello = {"address": path, "authkey": authkey.hex(), "parent": os.getpid()}
        self.process.stdin.write(json.dumps(hello).encode() + b"\n")
        self.process.stdin.flush()
        try:
            self._conn = self._accept(listener, authkey)
        except BaseException:
            self.kill()
            raise
        finally:
            listener.close()
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
        self._pending: dict[int, Future[Any]] = {}
        self._lock = threading.Lock()
        self._ids = itertools.count()
        self._closed = False
        self._reader = threading.Thread(
            target=self._read, name=f"worker-{host.name}-{self.pid}", daemon=True
        )
        self._reader.start()

    def __repr__(self) -> str:
        return f"<Worker {self.pid} on {self.host.name}>"

    def _accept(self, listener: socket.socket, authkey: bytes) -> Connection:
        """The worker's authenticated connection, or `WorkerDiedError` if it ends first."""
        pidfd = os.pidfd_open(self.pid)
        try:
            ready = _readable([listener, pidfd], START_TIMEOUT)
        finally:
            os.close(pidfd)
        if listener not in ready:
            if self.process.poll() is not None or ready:
                raise WorkerDiedError(f"{self!r} ended at start:\n{self.output()}")
            raise TimeoutError(f"{self!r} did not connect within {START_TIMEOUT:g} s")
        sock, _ = listener.accept()
        sock.setblocking(True)
        # a bound on the handshake's reads (blocking reads that fail after it, at the OS level:
        # `Connection` reads the descriptor directly), lifted once the worker is authenticated
        bound = struct.pack("ll", int(START_TIMEOUT), 0)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, bound)
        conn = Connection(sock.detach())
        deliver_challenge(conn, authkey)
        answer_challenge(conn, authkey)
        with socket.socket(fileno=os.dup(conn.fileno())) as view:
            view.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, struct.pack("ll", 0, 0))
        return conn

    def _read(self) -> None:
        """Hand each reply to its waiting call; at end of file fail every waiting call."""
        while True:
            try:
                call_id, ok, payload = self._conn.recv()
            except (EOFError, OSError):
                break
            with self._lock:
                future = self._pending.pop(call_id, None)
            if future is None:
                continue
            try:
                value = cloudpickle.loads(payload)
            except Exception as exc:
                future.set_exception(exc)
                continue
            if ok:
                future.set_result(value)
            else:
                exc, text = value
                exc.__cause__ = RemoteTraceback(text)
                future.set_exception(exc)
        with self._lock:
            self._closed = True
            waiting = list(self._pending.values())
            self._pending.clear()
        for future in waiting:
            future.set_exception(self._died())

    def _died(self) -> WorkerDiedError:
        try:  # (its end of the connection closes as it dies: the exit code comes at once)
            code: int | None = self.process.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            code = None
        how = "is gone" if code is None else f"ended with {code}"
        return WorkerDiedError(f"{self!r} {how}:\n{self.output()}")

    def output(self) -> str:
        """The last lines the worker wrote to stdout and stderr."""
        try:
            return self.log.read_text(errors="replace")[-3000:]
        except OSError:
            return ""

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def submit(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> Future[T]:
        """Run `fn(*args, **kwargs)` in the worker; the future holds its result or exception."""
        payload = _dumps_by_value((fn, args, kwargs))
        future: Future[T] = Future()
        with self._lock:
            if self._closed:
                raise self._died()
            call_id = next(self._ids)
            self._pending[call_id] = future
            try:
                self._conn.send((call_id, payload))
            except OSError as exc:
                self._pending.pop(call_id, None)
                raise self._died() from exc
        return future

    def call(self, fn: Callable[..., T], *args: Any, timeout: float, **kwargs: Any) -> T:
        """`fn(*args, **kwargs)` run in the worker: its result, or its exception re-raised here.

        Raises:
            TimeoutError: no answer within `timeout` seconds (the call goes on in the worker).
            WorkerDiedError: the worker ended before it answered.
        """
        future = self.submit(fn, *args, **kwargs)
        done, _ = futures_wait([future], timeout)
        if not done:  # (not `except TimeoutError`: a TimeoutError the worker raised, such as
            # rr.CallTimeoutError, is its answer, re-raised as it is)
            name = getattr(fn, "__qualname__", repr(fn))
            raise TimeoutError(f"{name} on {self!r}: no answer within {timeout:g} s")
        return future.result()

    def kill(self) -> None:
        """SIGKILL the worker and reap it."""
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.pid, signal.SIGKILL)
        self.process.wait(STOP_TIMEOUT)
        self._close_pipes()

    def stop(self) -> None:
        """Tell the worker to exit; SIGKILL it if it has not within `STOP_TIMEOUT`."""
        if self.alive:
            with contextlib.suppress(OSError):
                self._conn.send(None)
            try:
                self.process.wait(STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.kill()
        self._close_pipes()

    def _close_pipes(self) -> None:
        conn = getattr(self, "_conn", None)
        if conn is not None:
            with contextlib.suppress(OSError):
                conn.close()
        if self.process.stdin is not None:
            with contextlib.suppress(OSError):
                self.process.stdin.close()
        reader = getattr(self, "_reader", None)
        if reader is not None and reader is not threading.current_thread():
            reader.join(STOP_TIMEOUT)


def _kill_and_wait(pids: list[int]) -> None:
    """SIGKILL `pids` and wait (bounded) until each has ended (pidfds: children or not)."""
    pidfds = []
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            pidfds.append(os.pidfd_open(pid))
            os.kill(pid, signal.SIGKILL)
    try:
        for pidfd in pidfds:
            _readable([pidfd], STOP_TIMEOUT)
    finally:
        for pidfd in pidfds:
            os.close(pidfd)


def _pythonpath() -> list[str]:
    return [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]


class Host:
    """One side of a `TwoHosts`: a network namespace with one end of the veth (or, from
    `local_host`, this machine's own network, reached on loopback).

    Attributes:
        name: "a" or "b" ("local" for `local_host`).
        namespace: the network namespace's name (`None`: the test process's own).
        address: its IPv4 address on the veth (`10.77.<n>.1` or `.2`; `127.0.0.1`).
    """

    def __init__(self, name: str, namespace: str | None, address: str, directory: Path) -> None:
        self.name = name
        self.namespace = namespace
        self.address = address
        self._directory = directory
        self._workers: list[Worker] = []
        self._default: Worker | None = None

    def __repr__(self) -> str:
        return f"<Host {self.name} {self.address} in {self.namespace}>"

    def endpoint(self, port: int, protocol: str = "tcp") -> str:
        """The Zenoh endpoint `<protocol>/<address>:<port>` on this host (`tcp` or `tls`)."""
        return f"{protocol}/{self.address}:{port}"

    def spawn(self) -> Worker:
        """A new worker in this host's namespace (stopped with the host)."""
        worker = Worker(self, self._directory, len(self._workers))
        self._workers.append(worker)
        return worker

    @property
    def worker(self) -> Worker:
        """The host's default worker, started on first use (and again after `kill`)."""
        if self._default is None or not self._default.alive:
            self._default = self.spawn()
        return self._default

    def call(self, fn: Callable[..., T], *args: Any, timeout: float, **kwargs: Any) -> T:
        """`self.worker.call(fn, *args, timeout=timeout, **kwargs)`."""
        return self.worker.call(fn, *args, timeout=timeout, **kwargs)

    def kill(self) -> None:
        """SIGKILL the default worker (the next `call` starts a fresh one)."""
        if self._default is not None:
            self._default.kill()
            self._default = None

    def run(self, *command: str) -> str:
        """Run a command inside this host's namespace; its stdout (fails if it fails)."""
        inside = ["ip", "netns", "exec", self.namespace] if self.namespace else []
        done = subprocess.run(
            [*inside, *command],
            capture_output=True,
            text=True,
            check=False,
            timeout=30,
        )
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(command)} in {self.namespace}: {done.stderr.strip()}")
        return done.stdout

    def pids(self) -> list[int]:
        """Every process in this host's namespace (`ip netns pids`; none for a local host)."""
        if self.namespace is None:
            return []
        done = subprocess.run(
            ["ip", "netns", "pids", self.namespace],  # noqa: S607
            capture_output=True,
            text=True,
            check=False,
        )
        return [int(pid) for pid in done.stdout.split()]

    def close(self) -> None:
        """Stop every worker, then SIGKILL whatever they left running in the namespace."""
        for worker in reversed(self._workers):
            worker.stop()
        self._default = None
        _kill_and_wait(self.pids())


class TwoHosts:
    """Two network namespaces `a` and `b`, joined by a veth pair, each with its workers.

    Use as a context manager (or call `close`): leaving it stops every worker and deletes both
    namespaces, also after a failure.

    Args:
        outsider: also make host `c` (`10.78.<n>.3`), on a veth of its own to `a`
            (`10.78.<n>.1`), with its default route through `a`: it reaches every address
            of `a`'s, also while the link between `a` and `b` is down.

    Attributes:
        a, b: the two hosts (`10.77.<n>.1` and `10.77.<n>.2`, a /24 on the veth).
        c: the outsider (`None` unless asked for).
        directory: the 0700 directory of the workers' sockets and logs (deleted with them).
    """

    def __init__(self, *, outsider: bool = False) -> None:
        reason = require_root()
        if reason is not None:
            raise PermissionError(reason)
        if shutil.which("ip") is None:
            raise RuntimeError("two hosts need iproute2's `ip` (apt-get install -y iproute2)")
        sweep_stale()
        number = next(_numbers)
        self._made: list[str] = []
        self._tmp = tempfile.TemporaryDirectory(prefix="rr-hosts-")
        directory = self.directory = Path(self._tmp.name)
        directory.chmod(0o700)
        stem = f"{PREFIX}-{os.getpid()}-{number}"
        subnet = f"10.77.{number % 256}"
        self.a = Host("a", f"{stem}-a", f"{subnet}.1", directory)
        self.b = Host("b", f"{stem}-b", f"{subnet}.2", directory)
        self.c = Host("c", f"{stem}-c", f"10.78.{number % 256}.3", directory) if outsider else None
        try:
            for host in (self.a, self.b):
                _ip("netns", "add", host.namespace)
                self._made.append(host.namespace)
                _ip("-n", host.namespace, "link", "set", "lo", "up")
            _ip(
                *("-n", self.a.namespace, "link", "add", INTERFACE, "type", "veth"),
                *("peer", "name", INTERFACE, "netns", self.b.namespace),
            )
            for host in (self.a, self.b):
                _ip("-n", host.namespace, "addr", "add", f"{host.address}/24", "dev", INTERFACE)
            self.link_up()
            if self.c is not None:
                self._add_outsider(self.c, f"10.78.{number % 256}.1")
        except BaseException:
            self.close()
            raise

    def _add_outsider(self, c: Host, gateway: str) -> None:
        assert c.namespace is not None
        assert self.a.namespace is not None
        _ip("netns", "add", c.namespace)
        self._made.append(c.namespace)
        _ip("-n", c.namespace, "link", "set", "lo", "up")
        _ip(
            *("-n", self.a.namespace, "link", "add", OUTSIDE, "type", "veth"),
            *("peer", "name", OUTSIDE, "netns", c.namespace),
        )
        _ip("-n", self.a.namespace, "addr", "add", f"{gateway}/24", "dev", OUTSIDE)
        _ip("-n", c.namespace, "addr", "add", f"{c.address}/24", "dev", OUTSIDE)
        for namespace in (self.a.namespace, c.namespace):
            _ip("-n", namespace, "link", "set", OUTSIDE, "up")
        _ip("-n", c.namespace, "route", "add", "default", "via", gateway)

    def __enter__(self) -> TwoHosts:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def link_down(self) -> None:
        """Take the veth down on both ends (`ip link set rr0 down`): packets vanish, no FIN."""
        for host in (self.a, self.b):
            _ip("-n", host.namespace, "link", "set", INTERFACE, "down")

    def link_up(self) -> None:
        """Bring the veth up again on both ends (addresses and routes come back with it)."""
        for host in (self.a, self.b):
            _ip("-n", host.namespace, "link", "set", INTERFACE, "up")

    def close(self) -> None:
        """Stop every worker, then delete the namespaces (each step even if one fails)."""
        errors: list[BaseException] = []
        for host in (self.a, self.b, self.c):
            if host is None:
                continue
            try:
                host.close()
            except BaseException as exc:
                errors.append(exc)
        while self._made:
            with contextlib.suppress(RuntimeError):
                _ip("netns", "del", self._made.pop())
        self._tmp.cleanup()
        if errors:
            raise errors[0]


class ThreeHosts:
    """Three network namespaces in a line, `a` - `b` - `c`: two veth pairs, no link a-c.

    `a` and `c` have no route to each other (no veth, no forwarding): whatever passes
    between them goes through a process on `b` (a Zenoh router). Use as a context manager
    (or call `close`): leaving it stops every worker and deletes the namespaces.

        namespace ...-a              namespace ...-b                 namespace ...-c
        rr0 10.77.<n>.1 <--veth--> rr0 10.77.<n>.2
                                    rr2 10.79.<n>.2 <--veth--> rr2 10.79.<n>.3

    Attributes:
        a, b, c: the hosts (`b.address` is its address toward `a`; `b_toward_c` the one
            toward `c`).
        b_toward_c: `b`'s address on the b-c veth (`10.79.<n>.2`).
        directory: the 0700 directory of the workers' sockets and logs.
    """

    LINKS: ClassVar[dict[tuple[str, str], str]] = {("a", "b"): INTERFACE, ("b", "c"): "rr2"}
    """The veth of each pair of hosts, by its name in both namespaces."""

    def __init__(self) -> None:
        reason = require_root()
        if reason is not None:
            raise PermissionError(reason)
        if shutil.which("ip") is None:
            raise RuntimeError("three hosts need iproute2's `ip` (apt-get install -y iproute2)")
        sweep_stale()
        number = next(_numbers)
        self._made: list[str] = []
        self._tmp = tempfile.TemporaryDirectory(prefix="rr-hosts-")
        directory = self.directory = Path(self._tmp.name)
        directory.chmod(0o700)
        stem = f"{PREFIX}-{os.getpid()}-{number}"
        ab, bc = f"10.77.{number % 256}", f"10.79.{number % 256}"
        self.a = Host("a", f"{stem}-a", f"{ab}.1", directory)
        self.b = Host("b", f"{stem}-b", f"{ab}.2", directory)
        self.c = Host("c", f"{stem}-c", f"{bc}.3", directory)
        self.b_toward_c = f"{bc}.2"
        try:
            for host in (self.a, self.b, self.c):
                _ip("netns", "add", str(host.namespace))
                self._made.append(str(host.namespace))
                _ip("-n", str(host.namespace), "link", "set", "lo", "up")
            for (left, right), address_left, address_right in (
                (("a", "b"), self.a.address, self.b.address),
                (("b", "c"), self.b_toward_c, self.c.address),
            ):
                name = self.LINKS[left, right]
                one, other = self._host(left), self._host(right)
                _ip(
                    *("-n", str(one.namespace), "link", "add", name, "type", "veth"),
                    *("peer", "name", name, "netns", str(other.namespace)),
                )
                for host, address in ((one, address_left), (other, address_right)):
                    _ip("-n", str(host.namespace), "addr", "add", f"{address}/24", "dev", name)
                self.link_up(left, right)
        except BaseException:
            self.close()
            raise

    def _host(self, name: str) -> Host:
        return {"a": self.a, "b": self.b, "c": self.c}[name]

    def __enter__(self) -> ThreeHosts:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def _set(self, left: str, right: str, state: str) -> None:
        name = self.LINKS[left, right]
        for host in (self._host(left), self._host(right)):
            _ip("-n", str(host.namespace), "link", "set", name, state)

    def link_down(self, left: str, right: str) -> None:
        """Take the veth between `left` and `right` ("a", "b" or "b", "c") down on both
        ends: packets vanish, no FIN."""
        self._set(left, right, "down")

    def link_up(self, left: str, right: str) -> None:
        """Bring the veth between `left` and `right` up again on both ends."""
        self._set(left, right, "up")

    def close(self) -> None:
        """Stop every worker, then delete the namespaces (each step even if one fails)."""
        errors: list[BaseException] = []
        for host in (self.a, self.b, self.c):
            try:
                host.close()
            except BaseException as exc:
                errors.append(exc)
        while self._made:
            with contextlib.suppress(RuntimeError):
                _ip("netns", "del", self._made.pop())
        self._tmp.cleanup()
        if errors:
            raise errors[0]


@contextlib.contextmanager
def two_hosts() -> Iterator[TwoHosts]:
    """`TwoHosts()` for the duration of the block."""
    with TwoHosts() as hosts:
        yield hosts


@contextlib.contextmanager
def local_host() -> Iterator[Host]:
    """A `Host` on this machine's own network (loopback, no root needed), for the block."""
    with tempfile.TemporaryDirectory(prefix="rr-hosts-") as name:
        directory = Path(name)
        directory.chmod(0o700)
        host = Host("local", None, "127.0.0.1", directory)
        try:
            yield host
        finally:
            host.close()


def free_port() -> int:
    """A TCP port free on loopback right now (for listeners outside a namespace)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


# -- raw Zenoh in a worker (the harness's own tests and the benchmark's floor) -------------------
#
# Each function runs in a worker (sent by reference: `host.call(zenoh_open, ...)`) and keeps its
# session, queryables, tokens and events in the worker's `KEPT`.


def zenoh_config(
    *,
    listen: list[str] | tuple[str, ...] = (),
    connect: list[str] | tuple[str, ...] = (),
    lease: float | None = None,
) -> Any:
    """A peer's `zenoh.Config`: only the endpoints given (no scouting), `lease` in seconds."""
    import zenoh  # noqa: PLC0415 (only the workers that use Zenoh import it)

    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    if lease is not None:
        config.insert_json5("transport/link/tx/lease", str(round(lease * 1000)))
        config.insert_json5("transport/link/tx/keep_alive", "4")
    return config


def zenoh_open(
    *,
    listen: list[str] | tuple[str, ...] = (),
    connect: list[str] | tuple[str, ...] = (),
    lease: float | None = None,
) -> str:
    """Open this worker's Zenoh session (`KEPT["session"]`); its Zenoh id."""
    import zenoh  # noqa: PLC0415

    session = zenoh.open(zenoh_config(listen=listen, connect=connect, lease=lease))
    KEPT["session"] = session
    return str(session.zid())


def zenoh_echo(key: str) -> None:
    """Answer every query on `key` with its own payload (`b"pong"` if it has none)."""
    import zenoh  # noqa: PLC0415

    def answer(query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b"pong"
        query.reply(query.key_expr, payload)

    KEPT.setdefault("queryables", []).append(KEPT["session"].declare_queryable(key, answer))


def zenoh_token(key: str) -> None:
    """Declare a liveliness token on `key` (kept until the session closes)."""
    KEPT.setdefault("tokens", []).append(KEPT["session"].liveliness().declare_token(key))


def zenoh_watch(key: str) -> None:
    """Record liveliness changes on `key` (those already alive too) in `KEPT["events"]`."""
    import queue  # noqa: PLC0415
    import time  # noqa: PLC0415

    import zenoh  # noqa: PLC0415

    events: queue.Queue[tuple[str, str, float]] = queue.Queue()
    KEPT["events"] = events

    def record(sample: zenoh.Sample) -> None:
        kind = "put" if sample.kind == zenoh.SampleKind.PUT else "delete"
        events.put((kind, str(sample.key_expr), time.monotonic()))

    subscriber = KEPT["session"].liveliness().declare_subscriber(key, record, history=True)
    KEPT.setdefault("subscribers", []).append(subscriber)


def zenoh_next_event(timeout: float) -> tuple[str, str, float]:
    """The next recorded liveliness change: ("put" or "delete", key, `time.monotonic()`)."""
    import queue  # noqa: PLC0415

    try:
        event: tuple[str, str, float] = KEPT["events"].get(timeout=timeout)
    except queue.Empty:
        raise TimeoutError(f"no liveliness change within {timeout:g} s") from None
    return event


def zenoh_get(key: str, payload: bytes, timeout: float) -> bytes:
    """One `get` on `key`: the first good reply's payload (`LookupError` if none)."""
    for reply in KEPT["session"].get(key, payload=payload, timeout=timeout):
        if reply.ok is not None:
            answer: bytes = reply.ok.payload.to_bytes()
            return answer
    raise LookupError(f"no reply to a get on {key!r} within {timeout:g} s")


def zenoh_round_trips(key: str, rounds: int, warmup: int = 100) -> list[float]:
    """Seconds per `get` round trip on `key`, `rounds` times after `warmup` untimed ones."""
    import time  # noqa: PLC0415

    session = KEPT["session"]
    payload = b"x" * 200

    def once() -> None:
        for reply in session.get(key, payload=payload, timeout=5.0):
            if reply.ok is None:
                raise LookupError(f"an error reply to a get on {key!r}")

    for _ in range(warmup):
        once()
    samples = []
    for _ in range(rounds):
        start = time.perf_counter()
        once()
        samples.append(time.perf_counter() - start)
    return samples


# -- rr_actors in a worker (issue 22's API: `rr.ZenohNetwork`, `start(..., network=)`) ---------
#
# One `ZenohNetwork` per worker (a process belongs to one system), kept in its `KEPT` with the
# registrars it started there. `rr_run` runs any function with one of them in the worker.


def has_carrier() -> bool:
    """Whether this rr_actors has the Zenoh carrier (`rr.ZenohNetwork`) and the process layer
    that serves registrars on it (`ResourceRegistrar.start(..., network=)`)."""
    import inspect  # noqa: PLC0415

    import rr_actors as rr  # noqa: PLC0415

    start = inspect.signature(rr.ResourceRegistrar.start)
    return hasattr(rr, "ZenohNetwork") and "network" in start.parameters


# -- what a host's tests keep in `KEPT`: gates, flags and the statuses heard -----------------------


def wait_set(name: str, timeout: float) -> bool:
    """Whether the event `KEPT[name]` was set within `timeout` s (on the host it runs on)."""
    return bool(KEPT[name].wait(timeout))


def open_gate() -> None:
    """Set `KEPT["gate"]`: a load held at the gate ends."""
    KEPT["gate"].set()


def next_status(timeout: float) -> tuple[str, str, str, float]:
    """The next status a consumer's callback recorded in `KEPT["heard"]` (`TimeoutError`
    if none came within `timeout` s)."""
    heard: queue.Queue[tuple[str, str, str, float]] = KEPT.setdefault("heard", queue.Queue())
    try:
        return heard.get(timeout=timeout)
    except queue.Empty:
        raise TimeoutError(f"no status within {timeout:g} s") from None


def record_status(query: Any, update: Any) -> None:
    """A consumer's status callback: (query id, status name, source, when) into `KEPT`."""
    KEPT.setdefault("heard", queue.Queue()).put(
        (query.id, update.status.name, update.source, time.monotonic())
    )


def send_warning(registrar: Any, device: int) -> float:
    """A WARNING on the camera resource of `device`; when it was sent."""
    import rr_actors as rr  # noqa: PLC0415

    query_id = next(
        q.id for q in registrar.server_queries("camera") if q.request == {"device": device}
    )
    sent = time.monotonic()
    registrar.send_status(query_id, rr.Status.WARNING, "hot", timeout=5)
    return sent


def manager_pid(name: str) -> int:
    """The pid of manager `name` of this worker's supervisor (`KEPT["sup"]`)."""
    pid = KEPT["sup"].child(name).pid
    assert pid is not None
    return int(pid)


def stop_tree() -> None:
    """Stop this worker's supervisor (`KEPT["sup"]`), if it has one."""
    sup = KEPT.pop("sup", None)
    if sup is not None:
        sup.stop()


def more_statuses() -> int:
    """How many recorded statuses wait in `KEPT["heard"]`."""
    return int(KEPT.setdefault("heard", queue.Queue()).qsize())


def rr_join(
    *,
    system: str,
    listen: list[str],
    connect: list[str],
    lease: float = 1.0,
    tls: dict[str, Any] | None = None,
    resolve: str = "first_served",
) -> None:
    """Make this worker's `ZenohNetwork`: plain TCP (issue 22's step 1) or, with `tls` (the
    keyword arguments of `rr.ZenohTLS`), mutual TLS (step 2); `resolve` its rule 22
    strategy. Records from then on of the `rr_actors` logger, INFO and up, are kept in
    `KEPT["logs"]` (`rr_logs` reads them)."""
    import logging  # noqa: PLC0415

    import rr_actors as rr  # noqa: PLC0415

    records: list[tuple[str, str]] = []
    KEPT["logs"] = records

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append((record.levelname, record.getMessage()))

    log = logging.getLogger("rr_actors")
    log.addHandler(Keep(logging.INFO))
    log.setLevel(min(log.getEffectiveLevel(), logging.INFO))
    made = None if tls is None else rr.ZenohTLS(**tls)
    make = rr.ZenohNetwork
    KEPT["network"] = make(
        system=system, listen=listen, connect=connect, tls=made, lease=lease, resolve=resolve
    )
    KEPT["registrars"] = {}


def rr_logs(level: str | None = None) -> list[str]:
    """The messages `rr_join`'s handler kept (of `level` only, if given)."""
    return [message for name, message in KEPT["logs"] if level is None or name == level]


def rr_start(name: str, setup: Callable[[Any], object] | None = None) -> None:
    """Start registrar `name` in this worker, served on its network."""
    import rr_actors as rr  # noqa: PLC0415

    start: Any = rr.ResourceRegistrar.start
    KEPT["registrars"][name] = start(
        rr.RegistrarConfig(name=name), setup=setup, network=KEPT["network"]
    )


def rr_run(name: str, fn: Callable[..., T], *args: Any) -> T:
    """`fn(registrar, *args)` with this worker's registrar `name`."""
    return fn(KEPT["registrars"][name], *args)


def rr_until_answered(consumer: str, provider: str, server: str, timeout: float) -> None:
    """Call `provider/server` from `consumer` until it answers (its host may still be joining;
    a retry, not a sleep: each failure is immediate), then unload what was loaded."""
    import time  # noqa: PLC0415

    import rr_actors as rr  # noqa: PLC0415

    registrar = KEPT["registrars"][consumer]
    deadline = time.monotonic() + timeout
    while True:
        left = max(0.5, deadline - time.monotonic())
        try:
            query = registrar.call(provider, server, {"probe": 1}, timeout=min(5.0, left))
        except (rr.UnknownRegistrarError, rr.RegistrarUnavailableError, rr.CallTimeoutError):
            # (a call that timed out left nothing behind: rule 17; on a loaded machine the
            # first one over a link just up may be the one that takes too long)
            if time.monotonic() > deadline:
                raise
            continue
        registrar.unload(query.id)
        return


def rr_unlinked_within(name: str, timeout: float) -> bool:
    """Whether this worker's network stops seeing registrar `name` within `timeout` s."""
    from tests.support.waiting import wait_for  # noqa: PLC0415

    network = KEPT["network"]
    return bool(wait_for(lambda: name not in network.names(), timeout))


def names_within(name: str, timeout: float) -> bool:
    """Whether this worker's network sees registrar `name` within `timeout` seconds."""
    from tests.support.waiting import wait_for  # noqa: PLC0415

    network = KEPT["network"]
    return bool(wait_for(lambda: name in network.names(), timeout))


def rr_stop() -> None:
    """Stop this worker's registrars (newest first), then its network (if it has `close`)."""
    for registrar in reversed(list(KEPT.get("registrars", {}).values())):
        with contextlib.suppress(Exception):
            registrar.stop()
    close = getattr(KEPT.get("network"), "close", None)
    if close is not None:
        close()


# -- a flood of connections (an outsider's: `TwoHosts(outsider=True).c`) ------------------------


def flood(host: str, port: int, threads: int, sources: list[str] | None = None) -> None:
    """Start `threads` threads that connect to `host`:`port`, send a few bytes that are no
    TLS handshake, and close, as fast as they can (a connect gets 0.5 s), until
    `flood_stop`; `KEPT["flood"]` counts the attempts and the connections made. What a
    peer without a certificate does to a `tls/` port at its full rate (issue 29). With
    `sources` (addresses of this host), each connection comes from the next of them in
    turn (one machine's many addresses, issue 40)."""
    counts = {"attempts": 0, "connected": 0}
    stop = threading.Event()
    lock = threading.Lock()
    turns = itertools.cycle(sources or [None])

    def attack() -> None:
        while not stop.is_set():
            with lock:
                source = next(turns)
            with socket.socket() as conn:
                conn.settimeout(0.5)
                try:
                    if source is not None:
                        conn.bind((source, 0))
                    conn.connect((host, port))
                    conn.sendall(b"\x16\x03\x01\x00\x05hello")
                    made = 1
                except OSError:
                    made = 0
            with lock:
                counts["attempts"] += 1
                counts["connected"] += made

    workers = [threading.Thread(target=attack, daemon=True) for _ in range(threads)]
    KEPT["flood"] = (counts, stop, workers)
    for worker in workers:
        worker.start()


def flood_counts() -> dict[str, int]:
    """The flood's counts so far: {"attempts": n, "connected": n}."""
    return dict(KEPT["flood"][0])


def flood_stop() -> dict[str, int]:
    """Stop the flood (its threads end within a connect's 0.5 s); its counts."""
    counts, stop, workers = KEPT["flood"]
    stop.set()
    for worker in workers:
        worker.join(5.0)
    return dict(counts)


def _readable(files: list[Any], timeout: float) -> list[Any]:
    """Which of `files` (sockets or descriptors) are readable within `timeout` seconds.

    By `selectors` (epoll here), not `select.select`, which refuses a descriptor numbered
    1024 or more: a test process that opened many files meanwhile must still start hosts.
    """
    with selectors.DefaultSelector() as selector:
        for file in files:
            selector.register(file, selectors.EVENT_READ)
        return [key.fileobj for key, _ in selector.select(timeout)]
