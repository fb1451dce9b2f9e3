"""Display texts: bounded `repr`s of requests and responses, and resource labels.

Pure functions (the registrar runs them, `rr_actors._registrar.display`; observers only
show what they made). `is_plain` says whether a value's text can be made without running
user code: built-in strings, numbers and small containers of them.
"""

from __future__ import annotations

import reprlib
from collections.abc import Callable
from typing import Any

NOT_SHOWN_OLD = "<not shown: written by an older version>"
"""The display text of a value a version without display texts stored (before schema v4)."""

NOT_SHOWN_YET = "<not shown yet>"
"""What stands for a display text its registrar has not made yet (a `repr` on a worker)."""

TEXT_WIDTH = 80
"""Characters of a value's display text."""

LABEL_WIDTH = 40
"""Characters of a resource's label."""

_REPR = reprlib.Repr()  # (Python 3.11 takes no keyword arguments here)
_REPR.maxlevel = 3
_REPR.maxstring = _REPR.maxother = TEXT_WIDTH
_REPR.maxlong = 40
_REPR.maxdict = _REPR.maxlist = _REPR.maxtuple = _REPR.maxset = 6

_SCALARS = (str, bytes, int, float, complex, bool, type(None))
_SEQUENCES = (list, tuple)
_UNORDERED = (dict, set, frozenset)
_UNORDERED_MAX = 64  # reprlib sorts every key of these: beyond, the text goes to a worker


def _cut(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 3] + "..."


def display_text(value: Any) -> str:
    """A bounded `repr` of `value`; a failure is named in its place (never raises)."""
    try:
        text = _REPR.repr(value)
    except BaseException as exc:  # noqa: BLE001 - user code: SystemExit too is only shown
        return f"<repr failed: {type(exc).__name__}>"
    if type(text) is not str:
        return "<repr failed: not a string>"
    return _cut(text, TEXT_WIDTH)


def label_text(label: Callable[[Any], Any], request: Any) -> str:
    """What `label(request)` returned, cut to `LABEL_WIDTH`; a failure named instead."""
    try:
        text = label(request)
    except BaseException as exc:  # noqa: BLE001 - user code: SystemExit too is only shown
        return f"<label failed: {type(exc).__name__}>"
    if type(text) is not str:
        return f"<label failed: returned {type(text).__name__}>"
    return _cut(text, LABEL_WIDTH)


_SMALL = 2000  # characters and items a plain value may hold to be shown by `repr` itself
_TEXTS = (str, bytes)
_NUMBERS = (int, float, bool, type(None))


def _small(value: Any, budget: int) -> int:  # noqa: PLR0911 - one return per kind
    """What is left of `budget` after a plain value's items and characters (-1: over it,
    or not plain). Everything is looked at, so `repr` of a value within budget runs no
    user code and costs little."""
    kind = type(value)
    if kind in _TEXTS:
        return budget - len(value)
    if kind in _NUMBERS:
        return budget - 1 if kind is not int or -(10**60) < value < 10**60 else -1
    if kind in _SEQUENCES or kind is set or kind is frozenset:
        budget -= len(value)
        for item in value:
            if budget < 0:
                return -1
            budget = _small(item, budget)
        return budget
    if kind is dict:
        budget -= len(value)
        for key, item in value.items():
            if budget < 0:
                return -1
            budget = _small(item, _small(key, budget))
        return budget
    return -1


def plain_text(value: Any) -> str | None:
    """The display text of a plain value, made here (no user code runs); `None` for any
    other value (its `repr` is user code: run it on a worker, `display_text`)."""
    if _small(value, _SMALL) >= 0:
        return _cut(repr(value), TEXT_WIDTH)  # (the same text as reprlib's, faster)
    if is_plain(value):
        return display_text(value)
    return None


def is_plain(value: Any, level: int = _REPR.maxlevel) -> bool:
    """Whether `reprlib` shows `value` without running user code (bounded: it looks only
    as deep and as wide as `reprlib` does)."""
    kind = type(value)
    if kind in _SCALARS:
        return True
    if level <= 0:
        return kind in _SEQUENCES or kind in _UNORDERED  # shown as "[...]", not looked at
    if kind in _SEQUENCES:
        return all(is_plain(item, level - 1) for item in value[: _REPR.maxlist])
    if kind in _UNORDERED:
        if len(value) > _UNORDERED_MAX:
            return False
        items = value.items() if kind is dict else ((item, None) for item in value)
        return all(is_plain(k, level - 1) and is_plain(v, level - 1) for k, v in items)
    return False
