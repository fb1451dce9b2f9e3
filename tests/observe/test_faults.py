"""Teaching mode (`rr_actors_lab.observe._faults`): the faults the page's buttons inject, against a
real uvicorn on a loopback port, and what is refused."""

from __future__ import annotations

import os
import pickle
from typing import Any

import rr_actors as rr
from rr_actors_lab.observe import observe
from tests.support.observed_tree import REQUEST, erm_setup, figure_27
from tests.support.observing import (
    child,
    loaded,
    post_fault,
    process_state,
    request,
    stream,
    wait_state,
)

# -- teaching mode -------------------------------------------------------------------------------


def test_fault_buttons_are_refused_without_teaching_mode(tree: rr.Supervisor) -> None:
    observer = observe(tree)
    pid = tree.child("erm").pid

    status, answer = post_fault(observer.url, "kill", {"child": "erm", "pid": pid})

    assert (403, False) == (status, answer["ok"])
    assert pid == tree.child("erm").pid


def test_a_fault_without_the_token_is_refused(tree: rr.Supervisor) -> None:
    observer = observe(tree, allow_faults=True)
    pid = tree.child("erm").pid

    status, answer = post_fault(
        observer.url, "kill", {"child": "erm", "pid": pid}, with_token=False
    )

    assert 401 == status
    assert "token" in answer["message"]
    assert pid == tree.child("erm").pid


def test_a_fault_request_is_json_and_nothing_else_is_read(tree: rr.Supervisor) -> None:
    observer = observe(tree, allow_faults=True)
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
    observer = observe(tree, allow_faults=True)
    pid = tree.child("erm").pid
    assert pid is not None

    status, answer = post_fault(observer.url, "kill", {"child": "erm", "pid": os.getpid()})

    assert 409 == status
    assert "nothing was sent" in answer["message"]
    assert pid == tree.child("erm").pid


def test_the_kill_endpoint_kills_the_named_managers_process(tree: rr.Supervisor) -> None:
    observer = observe(tree, allow_faults=True)
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
    observer = observe(tree, allow_faults=True)
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
    observer = observe(sup, allow_faults=True)
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
    observer = observe(tree, allow_faults=True)
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
    observer = observe(tree, allow_faults=True)

    status, answer = post_fault(observer.url, "fatal", {"registrar": "erm", "resource_id": "nope"})

    assert (404, False) == (status, answer["ok"])


def test_a_thread_manager_has_no_process_to_kill(supervisors: Any) -> None:
    sup = figure_27(supervisors, isolation="thread").start()
    observer = observe(sup, allow_faults=True)

    status, answer = post_fault(observer.url, "kill", {"child": "erm", "pid": os.getpid()})

    assert 409 == status
    assert "thread manager" in answer["message"]


def test_a_fault_of_the_page_is_in_the_stream_as_an_event(tree: rr.Supervisor) -> None:
    observer = observe(tree, allow_faults=True)
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
