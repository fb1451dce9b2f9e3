"""Your copy of the supervisor's restart group (`rr-actors teach check` runs it in place
of the supervisor's own, in every supervisor of the simulated run).

When a child crashes, its supervisor stops some of the siblings too, in reverse start
order, then starts the whole group again in start order. Which siblings go with it is
the supervisor's strategy (OTP's): `one_for_one`, `one_for_all` or `rest_for_one`.
"""

from collections.abc import Sequence


def group(strategy: str, names: Sequence[str], crashed: str) -> list[str]:
    """The children a crash of `crashed` takes down with it, itself included.

    Args:
        strategy: the supervisor's: "one_for_one", "one_for_all" or "rest_for_one".
        names: every child's name, in the order they were started.
        crashed: the name of the child that crashed.

    Returns:
        The names of the children to stop and start again.
    """
    if strategy == "one_for_one":
        return [crashed]
    if strategy == "one_for_all":
        return list(names)
    # rest_for_one: a child needs the ones started before it, so restart those with it.
    return list(names[: names.index(crashed) + 1])
