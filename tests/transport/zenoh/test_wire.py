"""The key expressions (`zenoh.wire`): one parser per kind, `None` when malformed; `Keys`
builds each kind and parses back what it built."""

from __future__ import annotations

import hypothesis.strategies as st
import pytest
import zenoh
from hypothesis import given

from rr_actors._transport.zenoh.wire import (
    HostKey,
    Keys,
    NameAt,
    ServerKey,
)
from rr_actors.config import NAME

P = "rr/lab"
KEYS = Keys("lab")
ZID = "a0f481d091d919019faefa4c91471a5"


def test_well_formed_keys_say_what_their_tokens_mean() -> None:
    assert ZID == KEYS.parse_proc(f"{P}/live/proc/{ZID}")
    assert ServerKey("erm", ZID, "none", 1024, 7) == KEYS.parse_server(
        f"{P}/live/reg/erm/{ZID}/none/1024/7"
    )
    assert ServerKey("erm", ZID, "ab12", 1, 2**64 - 1) == KEYS.parse_server(
        f"{P}/live/reg/erm/{ZID}/ab12/1/{2**64 - 1}"
    )
    assert ServerKey("erm", ZID, "none", 1024, 7, side=2, members=3) == KEYS.parse_server(
        f"{P}/live/reg/erm/{ZID}/none/1024/7/2/3"
    )
    assert NameAt("erm", ZID) == KEYS.parse_claim(f"{P}/live/claim/erm/{ZID}")
    assert NameAt("erm", ZID) == KEYS.parse_stopped(f"{P}/live/stopped/erm/{ZID}")
    assert HostKey(ZID, 3) == KEYS.parse_host(f"{P}/live/host/{ZID}/3")


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
    assert KEYS.parse_proc(f"{P}/live/proc/{rest}") is None


@pytest.mark.parametrize(
    "rest",
    [
        f"erm/{ZID}/none/lots/1",
        f"erm/{ZID}/none/-1/1",
        f"erm/{ZID}/none/0/1",
        f"erm/{ZID}/none/01024/1",
        f"erm/{ZID}/none/1.5/1",
        f"erm/{ZID}/none/{'9' * 5000}/1",
        f"erm/{ZID}/none/\u0663/1",  # an Arabic-Indic digit: int() would take it
        f"erm/{ZID}/somebody/1024/1",
        "erm/not-hex/none/1024/1",
        f".hidden/{ZID}/none/1024/1",
        f"erm/{ZID}/none/1024",  # (a token of wire version 3: no stamp)
        f"erm/{ZID}/none/1024/soon",
        f"erm/{ZID}/none/1024/-1",
        f"erm/{ZID}/none/1024/007",
        f"erm/{ZID}/none/1024/{2**64}",  # past a clock stamp's 64 bits
        f"erm/{ZID}/none/1024/{'9' * 5000}",
        f"erm/{ZID}/none/1024/1/more",
        f"erm/{ZID}/none/1024/1/2/-3",  # (a side and a count of members: small numbers)
        f"erm/{ZID}/none/1024/1/02/3",
        f"erm/{ZID}/none/1024/1/2/{'9' * 50}",
        f"erm/{ZID}/none/1024/1/2/3/4",
    ],
)
def test_a_malformed_registrar_token_is_none(rest: str) -> None:
    assert KEYS.parse_server(f"{P}/live/reg/{rest}") is None


@pytest.mark.parametrize("rest", [ZID, f"{ZID}/-1", f"{ZID}/x", "not-hex/1", f"{ZID}/1/2"])
def test_a_malformed_host_token_is_none(rest: str) -> None:
    assert KEYS.parse_host(f"{P}/live/host/{rest}") is None


@pytest.mark.parametrize("parse", [KEYS.parse_claim, KEYS.parse_stopped])
@pytest.mark.parametrize("rest", ["erm/not-hex", "erm", f"erm/{ZID}/more", f"-x/{ZID}"])
def test_a_malformed_claim_or_stopped_mark_is_none(parse: object, rest: str) -> None:
    kind = "claim" if parse == KEYS.parse_claim else "stopped"
    assert parse(f"{P}/live/{kind}/{rest}") is None  # type: ignore[operator]


def test_a_key_of_another_system_is_none() -> None:
    assert KEYS.parse_proc(f"rr/other/live/proc/{ZID}") is None


# -- Keys: built, then parsed back ---------------------------------------------------------------

names = st.from_regex(NAME, fullmatch=True)
zids = st.from_regex(r"[0-9a-f]{1,32}", fullmatch=True)
servers = st.builds(
    ServerKey,
    names,
    zids,
    st.one_of(st.just("none"), zids),
    st.integers(1, 2**63 - 1),
    st.integers(0, 2**64 - 1),
    st.integers(0, 999_999),
    st.integers(0, 999_999),
)


@given(system=names, zid=zids)
def test_a_process_token_built_parses_back(system: str, zid: str) -> None:
    keys = Keys(system)
    assert "proc" == keys.kind(keys.proc(zid))
    assert zid == keys.parse_proc(keys.proc(zid))


@given(system=names, server=servers)
def test_a_registrar_token_built_parses_back(system: str, server: ServerKey) -> None:
    keys = Keys(system)
    assert "reg" == keys.kind(keys.server(server))
    assert server == keys.parse_server(keys.server(server))
    assert keys.parse_proc(keys.server(server)) is None  # (each parser takes its kind only)


@given(system=names, host=st.builds(HostKey, zids, st.integers(0, 999_999)))
def test_a_host_token_built_parses_back(system: str, host: HostKey) -> None:
    keys = Keys(system)
    assert ("host", host) == (keys.kind(keys.host(host)), keys.parse_host(keys.host(host)))
    assert keys.parse_server(keys.host(host)) is None


@given(system=names, at=st.builds(NameAt, names, zids))
def test_a_claim_and_a_stopped_mark_built_parse_back(system: str, at: NameAt) -> None:
    keys = Keys(system)
    assert ("claim", at) == (keys.kind(keys.claim(at)), keys.parse_claim(keys.claim(at)))
    assert ("stopped", at) == (keys.kind(keys.stopped(at)), keys.parse_stopped(keys.stopped(at)))
    assert keys.parse_stopped(keys.claim(at)) is None
    assert keys.parse_claim(Keys(f"{system}x").claim(at)) is None  # another system's


@given(key=st.one_of(st.text(), st.lists(st.text(), max_size=8).map("/".join)))
def test_parsing_any_string_is_a_value_never_an_exception(key: str) -> None:
    keys = Keys("lab")
    for head in ("", "rr/lab/live/proc/", "rr/lab/live/reg/", "rr/lab/live/claim/", "rr/lab/"):
        text = head + key
        assert isinstance(keys.kind(text), str)
        zid = keys.parse_proc(text)
        assert zid is None or keys.proc(zid) == text
        server = keys.parse_server(text)
        assert server is None or keys.server(server) == text
        claim, stopped = keys.parse_claim(text), keys.parse_stopped(text)
        assert claim is None or keys.claim(claim) == text
        assert stopped is None or keys.stopped(stopped) == text


def test_every_key_of_a_system_is_under_what_its_access_control_allows() -> None:
    keys, at = Keys("lab"), NameAt("erm", ZID)
    assert "rr/lab/**" == keys.everything()
    built = [
        keys.registrar("erm"),
        keys.answers(ZID),
        keys.ping(ZID),
        keys.proc(ZID),
        keys.server(ServerKey("erm", ZID, "none", 1024, 1)),
        keys.claim(at),
        keys.stopped(at),
    ]
    assert all(zenoh.KeyExpr(keys.everything()).includes(zenoh.KeyExpr(k)) for k in built)
    tokens = built[3:]  # what presence subscribes to, and asks of a name (not the process's)
    assert [k for k in built if zenoh.KeyExpr(keys.live()).includes(zenoh.KeyExpr(k))] == tokens
    of_erm = zenoh.KeyExpr(keys.live_of("erm"))
    assert [k for k in built if of_erm.includes(zenoh.KeyExpr(k))] == tokens[1:]
    assert not of_erm.includes(zenoh.KeyExpr(Keys("lab").claim(NameAt("erm2", ZID))))
    certificate = zenoh.KeyExpr(keys.certificate("robot"))  # (the handshake gate's: `members`)
    assert zenoh.KeyExpr(keys.everything()).includes(certificate)
    assert not zenoh.KeyExpr(keys.live()).includes(certificate)
