"""A wrong answer a student may write (the tests check that it fails): the children
started after the crashed one, but not the crashed one itself."""

from collections.abc import Sequence


def group(strategy: str, names: Sequence[str], crashed: str) -> list[str]:
    if strategy == "one_for_one":
        return [crashed]
    if strategy == "one_for_all":
        return list(names)
    return list(names[names.index(crashed) + 1 :])
