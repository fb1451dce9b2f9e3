"""The observer's server and event stream, against a real uvicorn on a loopback port."""

from __future__ import annotations

import os
import pickle
import signal
import socket
import time
from typing import Any

import pytest

import rr_actors as rr
from rr_actors.observe import Observer
from tests.support.observed_tree import REQUEST, erm_setup, figure_27
from tests.support.observing import (
    child,
    get_json,
    post_fault,
    process_state,
    request,
    stream,
    token,
    wait_state,
)


@pytest.fixture
def tree(supervisors: Any, process_helpers: Any) -> rr.Supervisor:
    """Figure 2.7's managers in processes, started; stopped at teardown."""
    return figure_27(supervisors).start()


def loaded(state: dict[str, Any]) -> bool:
    """Whether the observer shows figure 2.7 loaded: erm's 2 resources, cm's, action's query."""
    sections = state["sections"]

    def count(name: str, rows: str) -> int:
        section = sections.get(f"catalog/{name}")
        return len(section["catalog"][rows]) if section and section["catalog"] else 0

    graph = sections.get("graph") or {"edges": []}
    return (count("erm", "resources"), count("cm", "resources"), count("action", "clients")) == (
        2,
        1,
        1,
    ) and len(graph["edges"]) == 3


# -- the page ---------------------------------------------------------------------------------


def test_the_page_and_its_scripts_come_from_the_package_with_a_strict_policy(
    tree: rr.Supervisor,
) -> None:
    observer = tree.observe()

    page = request(observer.url, "/")
    script = request(observer.url, "/static/app.js")
    graph_library = request(observer.url, "/static/vendor/cytoscape.min.js")

    assert (200, 200, 200) == (page[0], script[0], graph_library[0])
    assert b"/static/vendor/cytoscape.min.js" in page[2]
    assert b"http" not in page[2].replace(b"http-equiv", b"")  # no remote resource at all
    assert "script-src 'self'" in page[1]["content-security-policy"]
    assert "nosniff" == page[1]["x-content-type-options"]


def test_the_observer_listens_on_loopback_at_a_free_port_by_default(tree: rr.Supervisor) -> None:
    observer = tree.observe()

    assert "127.0.0.1" == observer.host
    assert observer.url.startswith(f"http://127.0.0.1:{observer.port}/?token=")
    assert not observer.allow_faults


def test_the_state_shows_the_tree_the_catalogs_and_the_dependency_graph(
    tree: rr.Supervisor,
) -> None:
    observer = tree.observe()
    app = tree.registrar("action")
    query = app.call("cm", "filtered_camera", REQUEST)

    state = wait_state(observer.url, loaded)

    sections = state["sections"]
    assert ["erm", "cm"] == [c["name"] for c in sections["tree"]["children"]]
    assert tree.child("erm").pid == child(sections["tree"], "erm")["pid"]
    assert {"catalog/erm", "catalog/cm", "catalog/action"} <= set(sections)
    cm = sections["catalog/cm"]["catalog"]
    assert [query.id] == [c["query_id"] for c in cm["resources"][0]["consumers"]]
    assert 2 == sum(1 for c in cm["clients"] if c["parent"] == cm["resources"][0]["id"])
    edges = {
        (e["source"].split(":")[1], e["target"].split(":")[1]) for e in sections["graph"]["edges"]
    }
    assert {("action", "cm"), ("cm", "erm")} == edges  # figure 2.7: action -> cm -> erm
    app.unload(query.id)


# -- the event stream -------------------------------------------------------------------------


def test_the_stream_says_hello_then_sends_the_sections_then_the_events(
    tree: rr.Supervisor,
) -> None:
    observer = tree.observe()
    app = tree.registrar("action")

    with stream(observer.url) as events:
        name, hello = events.next()
        events.until(lambda s: "tree" in s.sections, timeout=10)
        query = app.call("cm", "filtered_camera", REQUEST)
        events.until(
            lambda s: any(
                e["type"] == "ResourceLoaded" and e["registrar"] == "cm" for e in s.events
            ),
            timeout=10,
        )

    assert ("hello", "live") == (name, hello["mode"])
    loaded = [e for e in events.events if e["type"] == "ResourceLoaded"]
    assert "cm/filtered_camera loaded" in " ".join(e["text"] for e in loaded)
    app.unload(query.id)


def test_a_sigkill_of_a_manager_reaches_the_stream_as_a_restart(tree: rr.Supervisor) -> None:
    observer = tree.observe()
    pid = tree.child("erm").pid
    assert pid is not None

    with stream(observer.url) as events:
        events.until(lambda s: "tree" in s.sections, timeout=10)
        os.kill(pid, signal.SIGKILL)
        took = events.until(lambda s: child(s.sections["tree"], "erm")["restarts"] == 1, 10)

    erm = child(events.sections["tree"], "erm")
    assert ("running", 1) == (erm["state"], erm["restarts"])
    assert pid != erm["pid"]
    assert "SIGKILL" in erm["last_exit"]
    assert took < 5.0


def test_a_backoff_shows_when_the_restart_is_due(supervisors: Any, process_helpers: Any) -> None:
    sup = figure_27(supervisors, backoff=rr.Backoff(initial=1.0, max=1.0, jitter=0.0)).start()
    observer = sup.observe()
    pid = sup.child("cm").pid
    assert pid is not None

    with stream(observer.url) as events:
        events.until(lambda s: "tree" in s.sections, timeout=10)
        killed_at = time.time()
        os.kill(pid, signal.SIGKILL)
        events.until(lambda s: child(s.sections["tree"], "cm")["restart_due"] is not None, 10)
        due = child(events.sections["tree"], "cm")["restart_due"]
        shown_at = events.sections["tree"]["server_time"]
        events.until(lambda s: child(s.sections["tree"], "cm")["state"] == "running", 10)

    # The 1 s backoff runs from when the exit was seen (after the kill) and was scheduled
    # before the page showed it: order, whatever the machine's load makes the gaps.
    assert killed_at + 1.0 <= due <= shown_at + 1.0
    assert due <= events.sections["tree"]["server_time"]  # restarted when due, not before
    assert child(events.sections["tree"], "cm")["restart_due"] is None


def test_a_status_reaches_the_stream_with_each_hop_and_its_latency(tree: rr.Supervisor) -> None:
    observer = tree.observe()
    app = tree.registrar("action")
    query = app.call("cm", "filtered_camera", REQUEST)

    with stream(observer.url) as events:
        events.until(lambda s: "tree" in s.sections, timeout=10)
        tree.run_in(
            "erm",
            lambda reg: reg.send_status(
                reg.server_queries("camera")[0].id, rr.Status.WARNING, "dusty lens"
            ),
        )
        tree.flush_events()
        events.until(
            lambda s: sum(e["type"] == "StatusDelivered" for e in s.events) >= 2, timeout=10
        )

    sent = next(e for e in events.events if e["type"] == "StatusSent")
    hops = sorted(
        (e["hop"], e["registrar"]) for e in events.events if e["type"] == "StatusDelivered"
    )
    assert ("erm", "WARNING", "dusty lens") == (sent["registrar"], sent["status"], sent["message"])
    assert [(1, "cm"), (2, "action")] == hops
    assert all(e["latency_s"] >= 0 for e in events.events if e["type"] == "StatusDelivered")
    app.unload(query.id)


def test_a_stream_ends_when_the_supervisor_stops(tree: rr.Supervisor) -> None:
    observer = tree.observe()

    with stream(observer.url) as events:
        events.until(lambda s: "tree" in s.sections, timeout=10)
        tree.stop()
        with pytest.raises(EOFError):
            events.until(lambda _: False, timeout=10)  # reads until the end

    assert observer.closed
    with pytest.raises(ConnectionRefusedError):
        request(observer.url, "/", timeout=2.0)


# -- bad input ----------------------------------------------------------------------------------


def test_another_host_header_is_refused(tree: rr.Supervisor) -> None:
    observer = tree.observe()  # a page of another site resolving its name to 127.0.0.1 ...

    status, _, _ = request(observer.url, "/api/state", headers={"Host": "evil.example:80"})

    assert 400 == status  # ... is refused (DNS rebinding)


def test_a_host_other_machines_reach_needs_allow_remote(tree: rr.Supervisor) -> None:
    with pytest.raises(rr.ConfigError, match="allow_remote"):
        tree.observe(host="0.0.0.0")  # noqa: S104 - what the test refuses


def test_allow_remote_binds_another_address_on_purpose(tree: rr.Supervisor) -> None:
    observer = tree.observe(host="0.0.0.0", allow_remote=True)  # noqa: S104 - on purpose

    status, _, _ = request(
        f"http://127.0.0.1:{observer.port}/",
        "/api/state",
        headers={"X-RR-Token": token(observer.url)},
    )

    assert 200 == status


def test_a_port_in_use_is_a_clear_error(tree: rr.Supervisor) -> None:
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    try:
        with pytest.raises(rr.ConfigError, match=f"port {taken.getsockname()[1]} .* in use"):
            tree.observe(port=taken.getsockname()[1])
    finally:
        taken.close()


@pytest.mark.parametrize("port", [-1, 70000, "80", True])
def test_a_bad_port_is_a_config_error(tree: rr.Supervisor, port: Any) -> None:
    with pytest.raises(rr.ConfigError, match="port"):
        tree.observe(port=port)


def test_a_stopped_supervisor_cannot_be_observed(tree: rr.Supervisor) -> None:
    tree.stop()

    with pytest.raises(rr.ConfigError, match="stopped"):
        tree.observe()


def test_an_observer_opened_before_the_start_sees_the_children_start(
    supervisors: Any, process_helpers: Any
) -> None:
    sup = figure_27(supervisors)
    observer = sup.observe()

    with stream(observer.url) as events:
        events.until(lambda s: "tree" in s.sections, timeout=10)
        sup.start()
        sup.flush_events()
        events.until(lambda s: sum(e["type"] == "ChildStarted" for e in s.events) == 2, 10)

    assert ["erm", "cm"] == [e["child"] for e in events.events if e["type"] == "ChildStarted"]


def test_an_observer_of_a_supervisor_that_never_started_closes_with_its_stop(
    supervisors: Any,
) -> None:
    sup = figure_27(supervisors, isolation="thread")
    observer = sup.observe()

    sup.stop()

    assert observer.closed


# -- teaching mode -------------------------------------------------------------------------------


def test_fault_buttons_are_refused_without_teaching_mode(tree: rr.Supervisor) -> None:
    observer = tree.observe()
    pid = tree.child("erm").pid

    status, answer = post_fault(observer.url, "kill", {"child": "erm", "pid": pid})

    assert (403, False) == (status, answer["ok"])
    assert pid == tree.child("erm").pid


def test_a_fault_without_the_token_is_refused(tree: rr.Supervisor) -> None:
    observer = tree.observe(allow_faults=True)
    pid = tree.child("erm").pid

    status, answer = post_fault(
        observer.url, "kill", {"child": "erm", "pid": pid}, with_token=False
    )

    assert 401 == status
    assert "token" in answer["message"]
    assert pid == tree.child("erm").pid


def test_a_fault_request_is_json_and_nothing_else_is_read(tree: rr.Supervisor) -> None:
    observer = tree.observe(allow_faults=True)
    pid = tree.child("erm").pid
    headers: dict[str, str] = {}
    pickled = pickle.dumps({"child": "erm", "pid": pid})

    as_form = request(
        observer.url, "/api/faults/kill", method="POST", body=pickled, headers=headers
    )
    headers["Content-Type"] = "application/json"
    as_json = request(
        observer.url, "/api/faults/kill", method="POST", body=pickled, headers=headers
    )

    assert (415, 400) == (as_form[0], as_json[0])  # never unpickled
    assert pid == tree.child("erm").pid


def test_a_kill_of_another_pid_than_the_managers_is_refused(tree: rr.Supervisor) -> None:
    observer = tree.observe(allow_faults=True)
    pid = tree.child("erm").pid
    assert pid is not None

    status, answer = post_fault(observer.url, "kill", {"child": "erm", "pid": os.getpid()})

    assert 409 == status
    assert "nothing was sent" in answer["message"]
    assert pid == tree.child("erm").pid


def test_the_kill_endpoint_kills_the_named_managers_process(tree: rr.Supervisor) -> None:
    observer = tree.observe(allow_faults=True)
    pid = tree.child("cm").pid
    assert pid is not None

    status, answer = post_fault(observer.url, "kill", {"child": "cm", "pid": pid})
    info = tree.wait_restarted("cm", timeout=10)

    assert (200, True) == (status, answer["ok"])
    assert (1, "killed by SIGKILL") == (info.restarts, info.last_exit)
    assert pid != info.pid
    assert 0 == tree.child("erm").restarts


def test_the_hang_endpoint_stops_the_process_and_its_heartbeat_gets_it_restarted(
    tree: rr.Supervisor, eventually: Any
) -> None:
    observer = tree.observe(allow_faults=True)
    pid = tree.child("erm").pid
    assert pid is not None

    status, answer = post_fault(observer.url, "hang", {"child": "erm", "pid": pid})
    stopped = eventually(lambda: process_state(pid) in ("T", None))  # T: stopped by a signal
    info = tree.wait_restarted("erm", timeout=10)

    assert (200, True) == (status, stopped)
    assert "0.75 s" in answer["message"]
    assert "hung" in (info.last_exit or "")


def test_the_resume_endpoint_lets_a_hung_manager_go_on(
    supervisors: Any, process_helpers: Any, eventually: Any
) -> None:
    sup = supervisors([rr.ManagerSpec("erm", erm_setup, isolation="process", heartbeat=None)])
    sup.start()
    observer = sup.observe(allow_faults=True)
    pid = sup.child("erm").pid
    assert pid is not None

    hung = post_fault(observer.url, "hang", {"child": "erm", "pid": pid})
    stopped = eventually(lambda: process_state(pid) == "T")
    resumed = post_fault(observer.url, "resume", {"child": "erm", "pid": pid})

    assert "no heartbeat" in hung[1]["message"]
    assert (True, 200) == (stopped, resumed[0])
    assert eventually(lambda: process_state(pid) in ("S", "R"))  # (SIGCONT takes a moment)
    assert 0 == sup.child("erm").restarts


def test_the_fatal_endpoint_reaches_every_consumer_up_the_chain(tree: rr.Supervisor) -> None:
    observer = tree.observe(allow_faults=True)
    heard: list[rr.StatusUpdate] = []
    app = tree.registrar("action")
    query = app.call("cm", "filtered_camera", REQUEST, on_status=lambda q, u: heard.append(u))
    state = wait_state(observer.url, loaded)
    camera = next(
        r
        for r in state["sections"]["catalog/erm"]["catalog"]["resources"]
        if r["server"] == "camera"
    )

    status, answer = post_fault(
        observer.url, "fatal", {"registrar": "erm", "resource_id": camera["id"]}
    )

    assert (200, True) == (status, answer["ok"])
    assert [(rr.Status.FATAL, "erm/camera")] == [(u.status, u.source) for u in heard]
    app.unload(query.id)


def test_a_fatal_on_an_unknown_resource_is_refused(tree: rr.Supervisor) -> None:
    observer = tree.observe(allow_faults=True)

    status, answer = post_fault(observer.url, "fatal", {"registrar": "erm", "resource_id": "nope"})

    assert (404, False) == (status, answer["ok"])


def test_a_thread_manager_has_no_process_to_kill(supervisors: Any) -> None:
    sup = figure_27(supervisors, isolation="thread").start()
    observer = sup.observe(allow_faults=True)

    status, answer = post_fault(observer.url, "kill", {"child": "erm", "pid": os.getpid()})

    assert 409 == status
    assert "thread manager" in answer["message"]


# -- text -----------------------------------------------------------------------------------------


def test_graph_draws_the_tree_and_figure_27_as_mermaid(tree: rr.Supervisor) -> None:
    app = tree.registrar("action")
    query = app.call("cm", "filtered_camera", REQUEST)

    text = tree.graph()

    assert text.startswith("flowchart TB\n")
    assert f'subgraph r1["erm · process manager · running · pid {tree.child("erm").pid}"]' in text
    assert "n1[\"'/dev/video0'\"]" in text  # (the server's only resource: its whole request)
    assert "s1 --> r1" in text
    assert "r3 -.-> n3" in text  # action -> cm's filtered camera (no query id drawn)
    assert 2 == text.count(" -.-> n1") + text.count(" -.-> n2")  # cm -> erm's two resources
    app.unload(query.id)


def test_graph_draws_dot_with_clusters(tree: rr.Supervisor) -> None:
    text = tree.graph(format="dot")

    assert text.startswith("digraph rr_actors {\n")
    assert "subgraph" not in text  # nothing loaded: registrars without resources are nodes
    assert 's1 [label="' in text
    assert "s1 -> r1;" in text


def test_graph_refuses_an_unknown_format(tree: rr.Supervisor) -> None:
    with pytest.raises(rr.ConfigError, match="mermaid, dot"):
        tree.graph(format="svg")


def test_the_observer_needs_the_observe_extra_to_serve(
    tree: rr.Supervisor, monkeypatch: pytest.MonkeyPatch
) -> None:
    import sys  # noqa: PLC0415

    import rr_actors.observe  # noqa: PLC0415

    monkeypatch.setitem(sys.modules, "rr_actors.observe._server", None)  # as if not installed
    monkeypatch.delattr(rr_actors.observe, "_server", raising=False)

    with pytest.raises(rr.MissingExtraError, match=r"needs an extra: pip install .*\[observe\]"):
        tree.observe()


def test_observer_is_a_context_manager(tree: rr.Supervisor) -> None:
    with tree.observe() as observer:
        assert isinstance(observer, Observer)
        assert "live" == get_json(observer.url, "/api/state")["hello"]["mode"]

    assert observer.closed


def test_a_fault_of_the_page_is_in_the_stream_as_an_event(tree: rr.Supervisor) -> None:
    observer = tree.observe(allow_faults=True)
    pid = tree.child("cm").pid

    with stream(observer.url) as events:
        events.until(lambda s: "tree" in s.sections, timeout=10)
        post_fault(observer.url, "kill", {"child": "cm", "pid": pid})
        events.until(lambda s: any(e["type"] == "ObserverFault" for e in s.events), timeout=10)
        events.until(lambda s: child(s.sections["tree"], "cm")["restarts"] == 1, timeout=10)

    fault = next(e for e in events.events if e["type"] == "ObserverFault")
    assert ("kill", f"SIGKILL sent to cm (pid {pid}); its supervisor restarts it") == (
        fault["kind"],
        fault["text"],
    )
