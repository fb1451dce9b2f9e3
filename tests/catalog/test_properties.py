"""Property-based tests driving real registrars (DESIGN rules 1-8).

A provider has a `leaf` server and a `composite` server whose load calls `leaf` for its
parts (nested loads, recorded as dependencies). A consumer loads, loads duplicates,
retries with a query id it already holds, unloads, and asks for requests flagged to fail
inside load: in the composite's callback itself or in one of its sub-loads. The provider
reports held resources `FATAL`: an equal request then loads a new one beside the dead
one. After each step the catalogs' invariants and consumer counts must hold; at the end
everything is unloaded and every successful load callback must be matched by exactly one unload
callback, per resource instance.
"""

from __future__ import annotations

import collections
import json
import threading
import uuid
from typing import Any

import hypothesis.strategies as st
import pytest
from hypothesis import HealthCheck, settings
from hypothesis.stateful import Bundle, RuleBasedStateMachine, consumes, invariant, rule

import rr_actors as rr
from rr_actors.testing import catalog_snapshot

KEYS = st.integers(0, 3)


def key_of(server: str, request: Any) -> str:
    return server + ":" + json.dumps(request, sort_keys=True)


class RegistrarMachine(RuleBasedStateMachine):
    held = Bundle("held")

    def __init__(self) -> None:
        super().__init__()
        suffix = uuid.uuid4().hex[:8]
        self.lock = threading.Lock()
        self.loaded: collections.Counter[str] = collections.Counter()  # successful loads
        self.unloaded: collections.Counter[str] = collections.Counter()
        self.holding: dict[str, rr.Query] = {}  # the consumer's top-level queries
        self.provider = rr.ResourceRegistrar.start(f"prop-provider-{suffix}")
        try:
            self.consumer = rr.ResourceRegistrar.start(f"prop-consumer-{suffix}")
        except BaseException:
            self.provider.stop()
            raise
        self.provider.register_server("leaf", load=self._leaf, unload=self._unload("leaf"))
        self.provider.register_server(
            "composite", load=self._composite, unload=self._unload("composite")
        )

    # -- the provider's callbacks (worker threads) ---------------------------------------

    def _leaf(self, request: dict[str, Any]) -> Any:
        if request["fail"]:
            raise RuntimeError(f"leaf {request['k']} refuses")
        with self.lock:
            self.loaded[key_of("leaf", request)] += 1
        return {"leaf": request["k"]}

    def _composite(self, request: dict[str, Any]) -> Any:
        parts = request["parts"]
        responses = []
        for i, k in enumerate(parts):
            fail = request["fail"] == "sub" and i == len(parts) - 1
            sub = {"k": k, "fail": fail}
            responses.append(self.provider.call(self.provider.name, "leaf", sub).response)
        if request["fail"] == "self":
            raise RuntimeError("composite refuses after loading its parts")
        with self.lock:
            self.loaded[key_of("composite", request)] += 1
        return responses

    def _unload(self, server: str) -> Any:
        def unload(request: Any, response: Any) -> None:
            with self.lock:
                self.unloaded[key_of(server, request)] += 1

        return unload

    # -- rules ----------------------------------------------------------------------------

    def _call(self, server: str, request: Any, fails: bool, query_id: str | None = None) -> Any:
        if fails:
            with pytest.raises(rr.ResourceLoadError):
                self.consumer.call(self.provider.name, server, request, query_id=query_id)
            return None
        query = self.consumer.call(self.provider.name, server, request, query_id=query_id)
        self.holding[query.id] = query
        return query

    @rule(target=held, k=KEYS, fail=st.booleans())
    def load_leaf(self, k, fail):
        return self._call("leaf", {"k": k, "fail": fail}, fail)

    @rule(
        target=held,
        parts=st.lists(KEYS, min_size=1, max_size=3),
        fail=st.sampled_from([None, None, "self", "sub"]),
    )
    def load_composite(self, parts, fail):
        return self._call("composite", {"parts": parts, "fail": fail}, fail is not None)

    @rule(target=held, query=held)
    def load_duplicate(self, query):
        if query is None:
            return None
        return self._call(query.server, json.loads(json.dumps(query.request)), False)

    @rule(query=held)
    def retry_with_the_same_query_id(self, query):
        if query is None or query.id not in self.holding:
            return
        again = self.consumer.call(
            self.provider.name, query.server, query.request, query_id=query.id
        )
        assert query == again

    @rule(query=held)
    def report_fatal(self, query):
        """The provider reports a held resource dead: later equal calls load a new one."""
        if query is None or query.id not in self.holding:
            return
        self.provider.send_status(query.id, rr.Status.FATAL, "it died")

    @rule(query=consumes(held))
    def unload(self, query):
        if query is None or query.id not in self.holding:
            return
        self.consumer.unload(query.id)
        del self.holding[query.id]

    @rule(query=held)
    def unload_twice_is_refused(self, query):
        if query is None or query.id in self.holding:
            return
        with pytest.raises(rr.UnknownQueryError):
            self.consumer.unload(query.id)

    # -- invariants -----------------------------------------------------------------------

    @invariant()
    def catalogs_are_consistent(self):
        provider = catalog_snapshot(self.provider)  # runs Catalog.check_invariants
        consumer = catalog_snapshot(self.consumer)
        assert set(self.holding) == {c.query.id for c in consumer.clients}
        assert all(c.parent is None and c.loaded for c in consumer.clients)

        by_id = {r.id: r for r in provider.resources}
        assert all(r.state.value == "loaded" and r.consumers for r in provider.resources)
        expected: collections.Counter[str] = collections.Counter(
            key_of(q.server, q.request) for q in self.holding.values()
        )
        for record in provider.clients:  # the composites' dependencies on leaves
            assert record.parent in by_id
            assert "composite" == by_id[record.parent].server
            expected[key_of("leaf", record.query.request)] += 1
        actual: collections.Counter[str] = collections.Counter()
        instances: collections.Counter[str] = collections.Counter()  # dead ones too
        matched: collections.Counter[str] = collections.Counter()  # not reported FATAL
        for r in provider.resources:
            actual[key_of(r.server, r.request)] += len(r.consumers)
            instances[key_of(r.server, r.request)] += 1
            matched[key_of(r.server, r.request)] += not r.failed
        assert expected == actual
        assert all(n <= 1 for n in matched.values())

        for resource in provider.resources:
            if resource.server == "composite":
                parts = [c.query.request["k"] for c in provider.clients if c.parent == resource.id]
                assert sorted(resource.request["parts"]) == sorted(parts)

        with self.lock:
            live = collections.Counter(self.loaded)
            live.subtract(self.unloaded)
        assert dict(instances) == {k: n for k, n in live.items() if n}

    def teardown(self):
        try:
            for query_id in reversed(list(self.holding)):
                self.consumer.unload(query_id)
            self.holding.clear()
            snapshot = catalog_snapshot(self.provider)
            assert ((), ()) == (snapshot.resources, snapshot.clients)
            assert self.loaded == self.unloaded
        finally:
            self.consumer.stop()
            self.provider.stop()


TestRegistrarMachine = RegistrarMachine.TestCase
TestRegistrarMachine.settings = settings(
    max_examples=50,
    stateful_step_count=20,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
