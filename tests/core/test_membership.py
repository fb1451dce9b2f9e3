"""The membership of a process: who is gone for good, told to each registrar of it once."""

from __future__ import annotations

from rr_actors._core.membership import Membership


class Hearer:
    """A joined hearer that writes down what it hears."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.heard: list[tuple[str, str]] = []
        self.batches: list[tuple[str, ...]] = []

    def peer_lost(self, name: str) -> None:
        self.heard.append(("lost", name))

    def peer_reachable(self, name: str) -> None:
        self.heard.append(("reachable", name))

    def peers_stopped(self, names: tuple[str, ...]) -> None:
        self.heard.extend(("stopped", name) for name in names)
        self.batches.append(names)

    def peer_started(self, name: str) -> None:
        self.heard.append(("started", name))


def test_a_stop_reported_by_each_registrar_of_the_process_is_told_to_each_once() -> None:
    # Each registrar here that another process tells of a stop reports it to the membership
    # (a death-watch mark to each): 3 reports must not be 3 x 3 tells (a tree of 300 on a
    # network stopped in hours: N x N tells per stopped registrar).
    membership = Membership()
    hearers = [Hearer(f"r{n}") for n in range(3)]
    for hearer in hearers:
        membership.join(hearer)
    for _ in hearers:
        membership.stopped("x", by="a death-watch mark")
    assert [hearer.heard for hearer in hearers] == [[("stopped", "x")]] * 3
    assert membership.gone() == {"x": True}


def test_a_registrar_stopped_again_after_it_came_back_is_told_again() -> None:
    membership = Membership()
    hearer = Hearer("r")
    membership.join(hearer)
    membership.stopped("x", by="its supervisor")
    membership.back("x")
    membership.stopped("x", by="its supervisor")
    assert hearer.heard == [("stopped", "x"), ("stopped", "x")]


def test_a_hearer_that_joins_after_a_stop_gets_it_at_join_and_is_not_told_again() -> None:
    membership = Membership()
    membership.stopped("x", by="its supervisor")
    late = Hearer("late")
    assert membership.join(late) == {"x": True}
    membership.stopped("x", by="a death-watch mark")
    assert late.heard == []


def test_a_stop_after_a_loss_is_still_told_and_the_loss_stays_recorded() -> None:
    membership = Membership()
    hearer = Hearer("r")
    membership.join(hearer)
    membership.lost("x", by="the death watch")
    membership.stopped("x", by="a death-watch mark")
    assert hearer.heard == [("lost", "x"), ("stopped", "x")]
    assert membership.gone() == {"x": False}


def test_a_start_is_told_only_to_the_hearers_that_monitor_it() -> None:
    # issue 69: a restart told to every registrar of a process took a turn of each (N)
    membership = Membership()
    caller, holder, bystander = Hearer("caller"), Hearer("holder"), Hearer("bystander")
    membership.join(caller)
    membership.join(holder, ["x"])  # (its restored rows name x)
    membership.join(bystander)
    membership.monitor("caller", "x")  # (a call to x)
    membership.started("x")
    assert [[("started", "x")], [("started", "x")], []] == [
        caller.heard,
        holder.heard,
        bystander.heard,
    ]


def test_a_hearer_monitoring_all_hears_every_start_until_it_stops() -> None:
    membership = Membership()
    restoring = Hearer("restoring")
    membership.monitor_all("restoring", on=True)  # (rows still unread)
    membership.join(restoring, ["x"])
    membership.started("y")
    membership.monitor_all("restoring", on=False)  # (each row swept)
    membership.started("z")
    membership.started("x")
    assert [("started", "y"), ("started", "x")] == restoring.heard


def test_a_tree_stop_told_at_once_is_one_batch_to_each_hearer_less_its_own_name() -> None:
    # A manager process told of the tree's stops so far (its supervisor's `PeersStopped`)
    # told its registrar a message a name: N x N messages in a tree of N process managers.
    membership = Membership()
    hearers = [Hearer("a"), Hearer("b")]
    for hearer in hearers:
        membership.join(hearer)
    membership.stopped("x", by="its supervisor")
    membership.stopped_all(["x", "y", "a", "z"], by="its supervisor (the tree's stop)")
    assert [h.batches for h in hearers] == [[("x",), ("y", "z")], [("x",), ("y", "a", "z")]]
    assert membership.gone() == {"x": True, "y": True, "a": True, "z": True}


class Reported:
    """A `Membership.report` that writes down what it is told."""

    def __init__(self) -> None:
        self.reports: list[tuple[str, object]] = []

    def monitoring(self, names: tuple[str, ...], at: float) -> None:
        self.reports.append(("monitoring", names))

    def hears_all(self, on: bool, at: float) -> None:
        self.reports.append(("hears_all", on))


def test_a_name_first_monitored_in_the_process_is_reported_once_and_after_it_is_recorded() -> None:
    # a manager process's supervisor tells it only the starts it reported (issue 69): each
    # name once, whichever of its registrars monitors it first
    membership = Membership()
    membership.report = report = Reported()
    membership.monitor("a", "x", "y")
    membership.monitor("b", "x")
    membership.monitor("a", "x", "a")
    assert [("monitoring", ("x", "y"))] == report.reports


def test_whether_any_registrar_hears_every_start_is_reported_only_when_it_changes() -> None:
    membership = Membership()
    membership.report = report = Reported()
    membership.monitor_all("a", on=True)
    membership.monitor_all("b", on=True)
    membership.monitor_all("a", on=False)
    membership.monitor_all("b", on=False)
    assert [("hears_all", True), ("hears_all", False)] == report.reports


def test_a_forked_child_reports_nothing_on_its_parents_pipe() -> None:
    membership = Membership()
    membership.report = report = Reported()
    membership.forget_in_child()
    membership.monitor("a", "x")
    assert [] == report.reports
