"""Bad input gets a clear rr_actors error, and nothing stored is lost."""

from __future__ import annotations

import threading
import uuid

import pytest

import rr_actors as rr
from rr_actors.testing import catalog_snapshot


def test_calling_an_unknown_registrar_raises_unknown_server_error(make_registrar):
    consumer = make_registrar("consumer")

    with pytest.raises(rr.UnknownServerError):
        consumer.call(f"nobody-{uuid.uuid4().hex[:8]}", "leaf", "x")

    assert () == catalog_snapshot(consumer).clients


def test_calling_an_unknown_server_raises_unknown_server_error(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "leaf")

    with pytest.raises(rr.UnknownServerError):
        consumer.call(provider.name, "nope", "x")

    assert () == catalog_snapshot(consumer).clients


@pytest.mark.parametrize("field", ["load", "unload", "on_status"])
def test_a_non_callable_callback_is_refused_and_nothing_is_registered(make_registrar, field):
    provider = make_registrar("provider")
    callbacks = {"load": lambda r: r, "unload": lambda r, s: None, "on_status": None}
    callbacks[field] = "not callable"

    with pytest.raises(rr.ConfigError, match=field):
        provider.register_server("leaf", **callbacks)

    with pytest.raises(rr.UnknownServerError):
        provider.server_queries("leaf")


def test_a_non_callable_status_callback_on_call_is_refused_before_anything_loads(
    make_registrar, serve
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    leaf = serve(provider, "leaf")

    with pytest.raises(rr.ConfigError):
        consumer.call(provider.name, "leaf", "x", on_status=42)  # type: ignore[arg-type]

    assert [] == leaf.loads


@pytest.mark.parametrize("name", ["", "a/b", 7])
def test_an_invalid_server_name_is_refused(make_registrar, name):
    provider = make_registrar("provider")

    with pytest.raises(rr.ConfigError):
        provider.register_server(name, load=lambda r: r, unload=lambda r, s: None)


def test_a_duplicate_server_name_is_refused_and_the_first_server_keeps_serving(
    make_registrar, serve
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    first = serve(provider, "leaf")
    held = consumer.call(provider.name, "leaf", "x")

    with pytest.raises(rr.DuplicateNameError):
        provider.register_server("leaf", load=lambda r: "imposter", unload=lambda r, s: None)

    assert [held] == provider.server_queries("leaf")
    assert {"resource": "y"} == consumer.call(provider.name, "leaf", "y").response
    assert ["x", "y"] == first.loads


@pytest.mark.thread_only(
    "starts a second registrar of that name in this process, where names are unique"
)
def test_a_duplicate_registrar_name_is_refused_and_the_first_keeps_running(make_registrar, serve):
    provider = make_registrar("provider")
    serve(provider, "leaf")
    held = provider.call(provider.name, "leaf", "x")

    with pytest.raises(rr.DuplicateNameError):
        rr.ResourceRegistrar.start(provider.name)

    assert [held] == provider.client_queries()


@pytest.mark.parametrize("config", ["", "has space", "a/b", 12, None])
def test_an_invalid_registrar_name_or_config_is_a_config_error(config):
    with pytest.raises(rr.ConfigError):
        rr.ResourceRegistrar.start(config)


@pytest.mark.parametrize("name", ["erm\n", "erm\r\n", "\nerm", "er\nm"])
@pytest.mark.parametrize(
    "spec",
    [
        rr.RegistrarConfig,
        rr.ManagerSpec,
        lambda name: rr.SupervisorSpec(name, ()),
    ],
    ids=["RegistrarConfig", "ManagerSpec", "SupervisorSpec"],
)
def test_a_name_with_a_line_break_is_a_config_error_naming_the_field(spec, name):
    with pytest.raises(rr.ConfigError, match="name"):
        spec(name)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("max_workers", 0),
        ("max_workers", 1.5),
        ("max_workers", True),
        ("compare_timeout", 0),
        ("compare_timeout", None),
        ("unload_timeout", -1.0),
    ],
)
def test_an_invalid_bound_on_user_code_is_a_config_error_naming_the_field(field, value):
    with pytest.raises(rr.ConfigError, match=field):
        rr.RegistrarConfig("erm", **{field: value})


@pytest.mark.parametrize(
    "method",
    [
        lambda reg, qid: reg.unload(qid),
        lambda reg, qid: reg.send_status(qid, rr.Status.OK, ""),
        lambda reg, qid: reg.update_response(qid, "r"),
        lambda reg, qid: reg.set_status_callback(qid, lambda q, u: None),
    ],
    ids=["unload", "send_status", "update_response", "set_status_callback"],
)
def test_an_unknown_query_id_raises_unknown_query_error_and_changes_nothing(
    make_registrar, serve, method
):
    provider = make_registrar("provider")
    serve(provider, "leaf")
    provider.call(provider.name, "leaf", "x")
    before = catalog_snapshot(provider)

    with pytest.raises(rr.UnknownQueryError):
        method(provider, str(uuid.uuid4()))

    assert before == catalog_snapshot(provider)


def test_an_invalid_status_code_is_a_config_error(make_registrar, serve):
    provider = make_registrar("provider")
    serve(provider, "leaf")
    query = provider.call(provider.name, "leaf", "x")

    with pytest.raises(rr.ConfigError):
        provider.send_status(query.id, "FATAL", "")  # type: ignore[arg-type]


def test_a_load_callback_that_raises_leaves_the_registrar_serving(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "good")
    held = consumer.call(provider.name, "good", "x")

    def broken(request):
        raise ZeroDivisionError("oops")

    serve(provider, "broken", broken)

    with pytest.raises(rr.ResourceLoadError):
        consumer.call(provider.name, "broken", "x")

    assert [held] == provider.server_queries("good")
    assert "y" == consumer.call(provider.name, "good", "y").response["resource"]


def test_a_load_callback_that_hangs_times_out_and_the_registrar_keeps_serving(
    make_registrar, serve, gates
):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    gate = gates()
    serve(provider, "hangs", lambda r: gate.wait(20))
    serve(provider, "good")

    with pytest.raises(rr.CallTimeoutError):
        consumer.call(provider.name, "hangs", "x", timeout=0.3)

    assert {"resource": "y"} == consumer.call(provider.name, "good", "y", timeout=5).response


def test_a_request_whose_equality_raises_is_treated_as_a_different_request(make_registrar, serve):
    class Touchy:
        def __eq__(self, other):
            raise RuntimeError("cannot compare")

        __hash__ = object.__hash__

    provider = make_registrar("provider")
    leaf = serve(provider, "leaf")

    provider.call(provider.name, "leaf", Touchy())
    provider.call(provider.name, "leaf", Touchy())

    assert 2 == len(leaf.loads)


def test_every_error_rr_actors_raises_derives_from_rr_error():
    errors = [getattr(rr, name) for name in rr.__all__ if name.endswith("Error")]

    assert all(issubclass(error, rr.RrError) for error in errors)
    assert issubclass(rr.CallTimeoutError, TimeoutError)


@pytest.mark.thread_only("a lock cannot even reach a manager process")
@pytest.mark.parametrize("policy", ["save_on_modify", "save_interval"])
def test_an_unpicklable_request_of_a_consumer_with_a_backup_is_a_config_error(
    make_registrar, serve, tmp_path, policy
):
    provider = make_registrar("provider")
    consumer = make_registrar(
        "consumer", backup_path=tmp_path / "c.db", save_on_modify=policy == "save_on_modify"
    )
    serve(provider, "leaf")

    with pytest.raises(rr.ConfigError, match="request"):
        consumer.call(provider.name, "leaf", threading.Lock(), timeout=5)

    assert consumer.is_alive()
    assert [] == provider.server_queries("leaf")
    assert {"resource": "fine"} == consumer.call(provider.name, "leaf", "fine").response
    consumer.save_catalog()  # (a save_interval flush stores what it holds)


@pytest.mark.thread_only("an unpicklable response cannot leave a manager process at all")
@pytest.mark.parametrize("policy", ["save_on_modify", "save_interval"])
def test_an_unpicklable_response_to_a_consumer_with_a_backup_is_a_config_error(
    make_registrar, tmp_path, policy
):
    provider = make_registrar("provider")  # no backup: it may hand any value on in-process
    consumer = make_registrar(
        "consumer", backup_path=tmp_path / "c.db", save_on_modify=policy == "save_on_modify"
    )
    provider.register_server("lock", load=lambda _r: threading.Lock(), unload=lambda _q, _r: None)

    with pytest.raises(rr.ConfigError, match="response"):
        consumer.call(provider.name, "lock", "x", timeout=5)

    assert consumer.is_alive()
    assert [] == provider.server_queries("lock")  # the id was given back
    assert [] == consumer.client_queries()
    consumer.save_catalog()


@pytest.mark.parametrize("value", [0, -1, True, 1.5, "1024", None])
def test_an_invalid_max_message_bytes_is_a_config_error_naming_it(value):
    with pytest.raises(rr.ConfigError, match="max_message_bytes"):
        rr.RegistrarConfig("erm", max_message_bytes=value)
