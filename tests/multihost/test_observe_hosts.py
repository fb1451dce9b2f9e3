"""The observer across hosts (issue 33, section 1), in a real browser, against two namespaces.

`hosts.TwoHosts`: host `a` (member `alpha`) and host `b` (`bravo`), one `ZenohNetwork`
each with mutual TLS (certificates from `tests/pki.py`); `b` dials `a`. Each runs a
supervisor with one process manager (`station` on `a`, `cam` on `b`) and opens its
observer (`observe(sup)`: across hosts, since the network is a `ZenohNetwork`); `a`'s
consumer registrar `app` holds a camera at `cam` (a dependency edge across hosts).

The browser (Debian's chromium, driven by Playwright from the test process) runs inside
`a`'s namespace (`nsenter --net`: a wrapper script given as its executable), so it opens
`a`'s page on `a`'s loopback, as a user on that machine would.

- `test_the_page_on_a_shows_both_hosts_and_bs_restart_after_a_sigkill`: both hosts'
  trees, grouped by member name, the cross-host edge, `b`'s catalog; a SIGKILL of `cam`
  on `b` shows on `a`'s page as its restart (`data-restarts` 0 -> 1) within `BOUND`.
- `test_a_fault_button_on_a_for_bs_manager_works_only_when_b_allowed_faults`: `b`
  opened its observer without `allow_faults`: the page says so, offers no button for
  `cam`, and a kill sent anyway (the page's own request) is refused by `b` with that
  reason; `b` opens it again with `allow_faults=True`: the button on `a`'s page kills
  `cam` (its supervisor restarts it).
- `test_rr_actors_observe_system_shows_every_host_from_a_process_without_a_tree`: a third
  member, `viewer`, in another process on `a`, runs `rr-actors observe --system lab
  --certs ... --connect ...` (`run_observe`): its page's state lists `alpha` and `bravo`
  live with their trees, and itself shares nothing.
- `test_a_cut_link_greys_bs_tree_then_it_is_live_after_the_heal`: `ip link set down`:
  within the lease (plus a bound for a loaded machine) the link shows cut (since when,
  why) and `b`'s tree greyed, its last known state kept; after `ip link set up` both are
  live again.

Screenshots go to `docs/img/` with `RR_DOCS_SCREENSHOTS=1` (as the one-host observer's).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import rr_actors as rr
from rr_actors_lab.observe import observe
from tests.support import hosts, pki
from tests.support.observing import CHROMIUM_ARGS, chromium

SYSTEM = "lab"
PORT = 7447
LEASE = 1.0
BOUND = 10.0  # seconds the page may take to show a remote restart (CI took 5.2 at stop 74)
CUT_BOUND = LEASE + 5.0  # seconds after a cut by which the page shows it
HEAL_BOUND = 30.0  # seconds after a heal by which the page is live again (Zenoh redials)
DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"

pytestmark = pytest.mark.timeout(240)


# -- what runs in the workers ------------------------------------------------------------------


def camera_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server(
        "camera", load=lambda request: {"stream": request}, unload=lambda _q, _r: None
    )


def station_setup(registrar: rr.ResourceRegistrar) -> None:
    registrar.register_server("plan", load=lambda request: request, unload=lambda _q, _r: None)


def start_tree(name: str, manager: str, state_dir: str) -> None:
    """A supervisor in this worker with one process manager (`cam` or `station`)."""
    setup = camera_setup if manager == "cam" else station_setup
    sup = rr.Supervisor(
        [rr.ManagerSpec(manager, setup=setup, isolation="process")],
        name=name,
        state_dir=state_dir,
        network=hosts.KEPT["network"],
    )
    sup.start()
    hosts.KEPT["sup"] = sup


def open_observer(allow_faults: bool) -> str:
    """(Re)open this host's observer; its URL."""
    old = hosts.KEPT.pop("observer", None)
    if old is not None:
        old.close()
    observer = observe(hosts.KEPT["sup"], allow_faults=allow_faults)
    hosts.KEPT["observer"] = observer
    return str(observer.url)


def hold_camera() -> str:
    """`app` (a consumer registrar of this host's supervisor) loads a camera at `cam`."""
    sup = hosts.KEPT["sup"]
    app = sup.registrar("app")
    deadline = time.monotonic() + 30
    while True:
        try:
            return str(app.call("cam", "camera", {"device": 1}, timeout=BOUND).id)
        except (rr.UnknownRegistrarError, rr.RegistrarUnavailableError, rr.CallTimeoutError):
            if time.monotonic() > deadline:
                raise


def stop_tree() -> None:
    observer = hosts.KEPT.pop("observer", None)
    if observer is not None:
        observer.close()
    sup = hosts.KEPT.pop("sup", None)
    if sup is not None:
        sup.stop()


# -- the test's side ---------------------------------------------------------------------------


@dataclasses.dataclass
class Lab:
    net: hosts.TwoHosts
    a: hosts.Worker
    b: hosts.Worker
    url: str


@pytest.fixture(scope="module")
def lab() -> Iterator[Lab]:
    reason = hosts.require_root()
    if reason is not None:
        pytest.skip(reason)
    with hosts.TwoHosts() as net:
        ca = pki.make_ca(net.directory, SYSTEM)
        members = ["alpha", "bravo", "viewer"]

        def tls(name: str, address: str) -> dict[str, Any]:
            cert, key = pki.issue(net.directory, name, [address], ca=ca)
            return {"ca": str(ca[0]), "cert": str(cert), "key": str(key), "members": members}

        a, b = net.a.spawn(), net.b.spawn()
        listen = f"tls/{net.a.address}:{PORT}"
        a.call(
            hosts.rr_join,
            system=SYSTEM,
            listen=[listen],
            connect=[],
            lease=LEASE,
            tls=tls("alpha", net.a.address),
            timeout=30,
        )
        b.call(
            hosts.rr_join,
            system=SYSTEM,
            listen=[],
            connect=[listen],
            lease=LEASE,
            tls=tls("bravo", net.b.address),
            timeout=30,
        )
        try:
            b.call(start_tree, "robot", "cam", str(net.directory / "b"), timeout=60)
            a.call(start_tree, "operator", "station", str(net.directory / "a"), timeout=60)
            b.call(open_observer, False, timeout=30)
            url = a.call(open_observer, True, timeout=30)
            a.call(hold_camera, timeout=60)
            tls("viewer", net.a.address)  # (its files, for the viewer's test)
            yield Lab(net, a, b, url)
        finally:
            for worker in (a, b):
                if worker.alive:
                    with contextlib.suppress(Exception):
                        worker.call(stop_tree, timeout=60)
                    with contextlib.suppress(Exception):
                        worker.call(hosts.rr_stop, timeout=30)


@pytest.fixture(scope="module")
def page(lab: Lab) -> Iterator[Any]:
    """A tab of a headless chromium that runs in host `a`'s network namespace."""
    import playwright.sync_api as playwright_api  # noqa: PLC0415 - the dev extra

    path = chromium()
    if path is None:
        pytest.fail("no chromium to drive (apt-get install -y chromium; .ci/run does)")
    with tempfile.TemporaryDirectory() as scratch:
        wrapper = Path(scratch) / "chromium-in-a"
        namespace = f"/run/netns/{lab.net.a.namespace}"
        wrapper.write_text(f'#!/bin/sh\nexec nsenter --net={namespace} {path} "$@"\n')
        wrapper.chmod(0o700)
        profile = Path(scratch) / "profile"
        with playwright_api.sync_playwright() as playwright:
            context = playwright.chromium.launch_persistent_context(
                str(profile),
                executable_path=str(wrapper),
                headless=True,
                args=CHROMIUM_ARGS,
                viewport={"width": 1500, "height": 1100},
            )
            tab = context.new_page()
            errors: list[str] = []
            tab.on("pageerror", lambda exc: errors.append(str(exc)))
            tab.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            tab.goto(lab.url)
            yield tab
            context.close()
            # (a refused fault request logs its 403 on the console: that one is expected)
            assert [] == [e for e in errors if "403" not in e]


def screenshot(page: Any, name: str, tmp_path: Path) -> None:
    where = DOCS_IMG if os.environ.get("RR_DOCS_SCREENSHOTS") == "1" else tmp_path
    page.screenshot(path=str(where / name), full_page=True)


def group(page: Any, member: str) -> Any:
    return page.locator(f'.host[data-member="{member}"]')


def cam(page: Any) -> Any:
    return group(page, "bravo").locator('.node[data-child="cam"]')


def state(page: Any) -> Any:
    """The page's `/api/state`, fetched by the page itself (the test cannot reach `a`)."""
    return page.evaluate("fetch('/api/state').then((r) => r.json())")


def post_fault(page: Any, kind: str, body: dict[str, Any]) -> tuple[int, Any]:
    """A fault request as the page's buttons send it (with its token); (status, answer)."""
    token = page.url.split("token=", 1)[1].split("&", 1)[0]
    script = """([kind, body, token]) => fetch(`/api/faults/${kind}`, {method: "POST",
        headers: {"Content-Type": "application/json", "X-RR-Token": token},
        body: JSON.stringify(body)}).then(async (r) => [r.status, await r.json()])"""
    status, answer = page.evaluate(script, [kind, body, token])
    return int(status), answer


def restarts(lab: Lab) -> int:
    return int(lab.b.call(restarts_of, "cam", timeout=10))


def restarts_of(name: str) -> int:
    return int(hosts.KEPT["sup"].child(name).restarts)


def test_the_page_on_a_shows_both_hosts_and_bs_restart_after_a_sigkill(
    lab: Lab, page: Any, tmp_path: Path
) -> None:
    before = restarts(lab)
    running = f'[data-state="running"][data-restarts="{before}"]'
    group(page, "bravo").locator(f'.node[data-child="cam"]{running}').wait_for(timeout=30_000)
    group(page, "alpha").locator('.node[data-child="station"][data-state="running"]').wait_for()
    page.wait_for_selector('#catalogs [data-member="bravo"] [data-registrar="cam"] .resource')
    page.wait_for_selector('[data-link="alpha|bravo"][data-up="yes"]')

    shown = state(page)["sections"]
    edges = [e for e in shown["graph"]["edges"] if e["crosses"]]
    assert [("reg:app", "cam")] == [(e["source"], e["target"].split(":")[1]) for e in edges]
    assert ["alpha", "bravo"] == [h["member"] for h in shown["hosts"]["hosts"]]
    assert "live" == group(page, "bravo").get_attribute("data-state")
    screenshot(page, "observer-hosts.png", tmp_path)

    killed = time.monotonic()
    os.kill(lab.b.call(hosts.manager_pid, "cam", timeout=10), signal.SIGKILL)
    cam(page).and_(page.locator(f'[data-restarts="{before + 1}"]')).wait_for(timeout=BOUND * 1000)
    took = time.monotonic() - killed

    assert "killed by SIGKILL" in cam(page).locator('[data-field="last-exit"]').inner_text()
    assert took < BOUND


def test_a_fault_button_on_a_for_bs_manager_works_only_when_b_allowed_faults(
    lab: Lab, page: Any, tmp_path: Path
) -> None:
    cam(page).and_(page.locator('[data-state="running"]')).wait_for(timeout=30_000)
    bravo = group(page, "bravo")
    assert "no faults" == bravo.locator(".host-faults").inner_text()
    assert 0 == bravo.locator("[data-fault]").count()
    assert 1 <= group(page, "alpha").locator("[data-fault]").count()  # a allowed its own
    pid = lab.b.call(hosts.manager_pid, "cam", timeout=10)

    status, answer = post_fault(page, "kill", {"child": "cam", "pid": pid, "host": "bravo"})

    assert 403 == status
    assert "bravo refused: bravo does not allow faults" in answer["message"]
    assert pid == lab.b.call(hosts.manager_pid, "cam", timeout=10)  # nothing was sent

    lab.b.call(open_observer, True, timeout=30)
    button = bravo.locator('[data-fault="kill"]')
    button.wait_for(timeout=30_000)
    assert "faults allowed" == bravo.locator(".host-faults").inner_text()
    before = restarts(lab)
    screenshot(page, "observer-hosts-faults.png", tmp_path)
    button.click()
    page.locator("#confirm-ok").click()
    cam(page).and_(page.locator(f'[data-restarts="{before + 1}"]')).wait_for(timeout=30_000)

    assert "from alpha's page" in json.dumps(
        [e for e in state(page)["events"] if e["type"] == "ObserverFault"]
    )
    assert pid != lab.b.call(hosts.manager_pid, "cam", timeout=10)


def view_system(argv: list[str], bound: float) -> dict[str, Any]:
    """Run `rr-actors observe` with `argv` in this worker until its page's `/api/state` shows
    `alpha` and `bravo` live with their trees (at most `bound` s); that state."""
    import io  # noqa: PLC0415
    import re  # noqa: PLC0415
    import threading  # noqa: PLC0415
    import urllib.request  # noqa: PLC0415

    from rr_actors_lab.__main__ import build_parser  # noqa: PLC0415
    from rr_actors_lab.observe._commands import run_observe  # noqa: PLC0415

    printed = threading.Event()

    class Out(io.StringIO):
        def write(self, text: str) -> int:
            written = super().write(text)
            printed.set()
            return written

    out, stop = Out(), threading.Event()
    args = build_parser().parse_args(["observe", *argv])
    thread = threading.Thread(target=run_observe, args=(args, out), kwargs={"stop": stop})
    thread.start()
    try:
        assert printed.wait(bound), "rr-actors observe printed no URL"
        match = re.search(r"(http://\S+)\?token=(\S+)", out.getvalue())
        assert match is not None, out.getvalue()
        url = f"{match[1]}api/state"
        request = urllib.request.Request(url, headers={"X-RR-Token": match[2]})  # noqa: S310
        deadline = time.monotonic() + bound
        while True:
            with urllib.request.urlopen(request, timeout=bound) as answer:  # noqa: S310
                shown: dict[str, Any] = json.loads(answer.read())
            hosts_shown = shown["sections"].get("hosts", {}).get("hosts", [])
            live = {h["member"] for h in hosts_shown if h["state"] == "live"}
            trees = {k for k in shown["sections"] if k.endswith("/tree")}
            if {"alpha", "bravo"} <= live and {"host/alpha/tree", "host/bravo/tree"} <= trees:
                return shown
            if time.monotonic() > deadline:
                raise TimeoutError(f"not every host live within {bound:g} s: {hosts_shown}")
            stop.wait(0.1)  # (a poll of a real page, bounded)
    finally:
        stop.set()
        thread.join(bound)


def test_rr_actors_observe_system_shows_every_host_from_a_process_without_a_tree(
    lab: Lab,
) -> None:
    viewer = lab.net.a.spawn()
    argv = [
        *("--system", SYSTEM, "--certs", str(lab.net.directory)),
        *("--name", "viewer", "--members", "alpha,bravo,viewer"),
        *("--connect", f"tls/{lab.net.a.address}:{PORT}", "--lease", str(LEASE)),
    ]
    try:
        shown = viewer.call(view_system, argv, 30.0, timeout=60)
    finally:
        viewer.stop()

    assert ["alpha", "bravo"] == [h["member"] for h in shown["sections"]["hosts"]["hosts"]]
    assert "viewer" == shown["hello"]["member"]
    assert "cam" == shown["sections"]["host/bravo/tree"]["children"][0]["name"]


def test_a_cut_link_greys_bs_tree_then_it_is_live_after_the_heal(
    lab: Lab, page: Any, tmp_path: Path
) -> None:
    cam(page).and_(page.locator('[data-state="running"]')).wait_for(timeout=30_000)
    group(page, "bravo").and_(page.locator('[data-state="live"]')).wait_for(timeout=30_000)
    pid = lab.b.call(hosts.manager_pid, "cam", timeout=10)

    cut = time.monotonic()
    lab.net.link_down()
    try:
        page.wait_for_selector('[data-link="alpha|bravo"][data-up="no"]', timeout=CUT_BOUND * 1000)
        group(page, "bravo").and_(page.locator('[data-state="stale"]')).wait_for(
            timeout=CUT_BOUND * 1000
        )
        took = time.monotonic() - cut
        note = group(page, "bravo").locator(".stale-note").inner_text()
        link = page.locator('[data-link="alpha|bravo"]').inner_text()
        assert f"pid {pid}" == cam(page).locator('[data-field="pid"]').inner_text()  # last known
        screenshot(page, "observer-hosts-cut.png", tmp_path)
    finally:
        lab.net.link_up()
    healed = time.monotonic()
    group(page, "bravo").and_(page.locator('[data-state="live"]')).wait_for(
        timeout=HEAL_BOUND * 1000
    )
    page.wait_for_selector('[data-link="alpha|bravo"][data-up="yes"]', timeout=HEAL_BOUND * 1000)
    back = time.monotonic() - healed

    assert took < CUT_BOUND
    assert "stale since" in note
    assert "closed" in note  # why: the link watch saw the link to bravo close
    assert "cut since" in link
    assert back < HEAL_BOUND
