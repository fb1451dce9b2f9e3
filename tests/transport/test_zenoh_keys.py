"""The liveliness key expressions (`zenoh_wire`): one parser per kind, `None` when malformed."""

from __future__ import annotations

import pytest

from rr_actors._transport.zenoh_wire import (
    NameAt,
    ServerKey,
    claim_key,
    proc_key,
    server_key,
    stopped_key,
)

P = "rr/lab"
ZID = "a0f481d091d919019faefa4c91471a5"


def test_well_formed_keys_say_what_their_tokens_mean() -> None:
    assert ZID == proc_key(f"{P}/live/proc/{ZID}", P)
    assert ServerKey("erm", ZID, "none", 1024) == server_key(f"{P}/live/reg/erm/{ZID}/none/1024", P)
    assert ServerKey("erm", ZID, "ab12", 1) == server_key(f"{P}/live/reg/erm/{ZID}/ab12/1", P)
    assert NameAt("erm", ZID) == claim_key(f"{P}/live/claim/erm/{ZID}", P)
    assert NameAt("erm", ZID) == stopped_key(f"{P}/live/stopped/erm/{ZID}", P)


@pytest.mark.parametrize(
    "rest",
    [
        "not-hex",
        "ABCDEF",
        "a" * 33,
        "",
        f"{ZID}/extra",
    ],
)
def test_a_malformed_process_token_is_none(rest: str) -> None:
    assert proc_key(f"{P}/live/proc/{rest}", P) is None


@pytest.mark.parametrize(
    "rest",
    [
        f"erm/{ZID}/none/lots",
        f"erm/{ZID}/none/-1",
        f"erm/{ZID}/none/0",
        f"erm/{ZID}/none/1.5",
        f"erm/{ZID}/none/{'9' * 5000}",
        f"erm/{ZID}/none/\u0663",  # an Arabic-Indic digit: int() would take it
        f"erm/{ZID}/somebody/1024",
        "erm/not-hex/none/1024",
        f".hidden/{ZID}/none/1024",
        f"erm/{ZID}/none",
        f"erm/{ZID}/none/1024/more",
    ],
)
def test_a_malformed_registrar_token_is_none(rest: str) -> None:
    assert server_key(f"{P}/live/reg/{rest}", P) is None


@pytest.mark.parametrize("parse", [claim_key, stopped_key])
@pytest.mark.parametrize("rest", ["erm/not-hex", "erm", f"erm/{ZID}/more", f"-x/{ZID}"])
def test_a_malformed_claim_or_stopped_mark_is_none(parse: object, rest: str) -> None:
    kind = "claim" if parse is claim_key else "stopped"
    assert parse(f"{P}/live/{kind}/{rest}", P) is None  # type: ignore[operator]


def test_a_key_of_another_system_is_none() -> None:
    assert proc_key(f"rr/other/live/proc/{ZID}", P) is None
