"""A consumer lost for good gives up the loads it has under way too (rule 19).

A provider that hears that a consumer is gone and will not come back (`ConsumerDown`
from a death watch, or a carrier's `peer_lost`) releases the ids the consumer holds and
gives up the loads it is still waiting for: each is unloaded once its load ends. The
provider must not count on its answer to the dead consumer failing: over Zenoh an answer
put to a process whose token has not gone yet is dropped by the network without a word.
The consumer here stays alive, so its answer would reach it: only the give-up releases it.
"""

from __future__ import annotations

import contextlib
import threading

import rr_actors as rr


def _say_consumer_down(registrar: rr.ResourceRegistrar, consumer: str) -> None:
    # (imported here: this module is pickled by value, the directory must not be)
    from rr_actors._core.directory import DIRECTORY  # noqa: PLC0415
    from rr_actors._registrar.messages import ConsumerDown  # noqa: PLC0415

    DIRECTORY.lookup(registrar.name).tell(ConsumerDown(consumer))


def _call_ignoring_errors(consumer, provider_name):
    with contextlib.suppress(rr.RrError):  # answered as given up
        consumer.call(provider_name, "slow", "x", timeout=10)


def test_a_consumer_lost_while_its_load_runs_is_released_when_the_load_ends(
    make_registrar, serve, gated_load
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    slow = gated_load()
    leaf = serve(provider, "slow", slow)
    caller = threading.Thread(target=_call_ignoring_errors, args=(consumer, provider.name))
    caller.start()
    assert slow.started.wait(5)

    gone = consumer.name
    if isinstance(provider, rr.ResourceRegistrar):
        _say_consumer_down(provider, gone)
    else:
        provider.run(lambda registrar: _say_consumer_down(registrar, gone))
    slow.gate.set()
    caller.join(10)

    assert leaf.unloaded.wait(5)
    assert [] == provider.server_queries("slow")
