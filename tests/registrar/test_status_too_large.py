"""A status or a new response its consumer cannot take is a `MessageTooLargeError` for its sender.

A status message over the receiving registrar's `max_message_bytes` used to be dropped
without a word: `send_status(FATAL, ...)` returned as if every consumer had heard it, and
the consumer went on using a resource its provider had reported dead (rule 9). Now the
sender gets the error naming the registrar not reached (`MessageTooLargeError`
promises this), the provider's log says so, and the FATAL mark stands (rule 1). A new
response (`update_response`) was only logged: its caller now hears of it too.
"""

from __future__ import annotations

import pytest

import rr_actors as rr

LIMIT = 100_000
"""The consumer's `max_message_bytes`."""


@pytest.mark.across_processes("a message's size counts only where it is pickled")
def test_a_fatal_whose_message_is_over_the_consumers_limit_fails_its_sender_naming_it(
    make_registrar, serve, inbox
):
    provider = make_registrar("provider")
    consumer = make_registrar("consumer", max_message_bytes=LIMIT)
    leaf = serve(provider, "leaf")
    heard = inbox()
    dead = consumer.call(provider.name, "leaf", "lidar", on_status=heard, timeout=10)

    with pytest.raises(rr.MessageTooLargeError, match=consumer.name):
        provider.send_status(dead.id, rr.Status.FATAL, "x" * (2 * LIMIT), timeout=10)

    provider.send_status(dead.id, rr.Status.FATAL, "the LiDAR died", timeout=10)
    assert [(dead.id, rr.Status.FATAL, "the LiDAR died")] == [
        (u.query_id, u.status, u.message) for _, u in heard.updates
    ]
    consumer.call(provider.name, "leaf", "lidar", timeout=10)  # marked at the first FATAL:
    assert ["lidar", "lidar"] == leaf.loads  # a new resource for an equal request


@pytest.mark.across_processes("a message's size counts only where it is pickled")
def test_a_new_response_over_a_consumers_limit_fails_update_response_naming_it(
    make_registrar, serve
):
    provider = make_registrar("provider")
    consumer = make_registrar("consumer", max_message_bytes=LIMIT)
    serve(provider, "leaf")
    held = consumer.call(provider.name, "leaf", "lidar", timeout=10)

    with pytest.raises(rr.MessageTooLargeError, match=consumer.name):
        provider.update_response(held.id, "x" * (2 * LIMIT), timeout=10)

    provider.update_response(held.id, "repaired", timeout=10)
    assert ["repaired"] == [q.response for q in consumer.client_queries(timeout=10)]
