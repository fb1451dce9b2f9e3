"""`rr_actors.testing.MemoryNetwork` used carelessly: a cut of a name never served, a
negative timeout.

`cut(name)` stands for a SIGKILL in a test; a typo in `name` used to cut nothing, and the
test went on as if the registrar's process were gone (and could pass for it).
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import pytest

import rr_actors as rr
from rr_actors.testing import MemoryNetwork


@pytest.fixture
def served() -> Iterator[tuple[MemoryNetwork, rr.ResourceRegistrar]]:
    """A network with one registrar `erm-<hex>` served on it."""
    network = MemoryNetwork(f"misuse-{uuid.uuid4().hex[:8]}")
    erm = rr.ResourceRegistrar.start(
        rr.RegistrarConfig(name=f"erm-{uuid.uuid4().hex[:8]}"), network=network
    )
    try:
        yield network, erm
    finally:
        erm.stop()
        network.close()


def test_cutting_a_name_never_served_is_an_unknown_registrar_error_naming_the_served_ones(
    served: tuple[MemoryNetwork, rr.ResourceRegistrar],
) -> None:
    network, erm = served
    typo = erm.name + "x"

    with pytest.raises(rr.UnknownRegistrarError, match=f"did you mean '{erm.name}'"):
        network.cut(typo)

    assert [erm.name] == network.names()  # nothing was cut


def test_cutting_a_registrar_twice_is_no_error(
    served: tuple[MemoryNetwork, rr.ResourceRegistrar],
) -> None:
    network, erm = served
    network.cut(erm.name)

    network.cut(erm.name)

    assert [] == network.names()


def test_run_with_a_timeout_that_is_not_positive_is_a_config_error(
    served: tuple[MemoryNetwork, rr.ResourceRegistrar],
) -> None:
    network, erm = served

    with pytest.raises(rr.ConfigError, match="timeout"):
        network.run(erm.name, lambda r: r.name, timeout=-1)
