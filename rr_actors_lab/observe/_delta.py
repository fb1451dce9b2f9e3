"""What changed between two versions of a section, as a small JSON patch the page applies.

```
 old value ─┐
            ├─ diff ──► patch ── one encoding, shared by every page ──► app.js applyPatch
 new value ─┘
```

A patch is a JSON object with exactly one of these keys:

- `{"v": value}`: the value is replaced whole;
- `{"d": {key: patch, ...}, "x": [key, ...]}`: a dict's changed keys and removed ones;
- `{"l": {id: patch, ...}, "k": field, "x": [id, ...], "i": [[index, id], ...]}`: a list
  of rows with a unique id in `field` (`"id"`, `"query_id"` or `"name"`): rows changed or
  added, removed, and the added rows' ascending indexes; `"o"` the whole new order when
  the kept rows were reordered.
"""

from __future__ import annotations

from typing import Any

__all__ = ["apply", "diff"]

_KEYS = ("id", "query_id", "name")


def _row_key(old: list[Any], new: list[Any]) -> str | None:
    """The field that identifies each row of both lists (`None`: they are not rows with ids)."""
    if not (old or new) or not all(isinstance(r, dict) for r in (*old, *new)):
        return None
    for key in _KEYS:
        if all(_unique_ids(rows, key) for rows in (old, new)):
            return key
    return None


def _unique_ids(rows: list[dict[str, Any]], key: str) -> bool:
    ids = [r.get(key) for r in rows]
    return all(isinstance(i, str) for i in ids) and len(set(ids)) == len(ids)


def diff(old: Any, new: Any) -> dict[str, Any] | None:
    """The patch that turns `old` into `new` (`None`: they are equal)."""
    if old == new:
        return None
    if isinstance(old, dict) and isinstance(new, dict):
        changed = {}
        for key, value in new.items():
            if key not in old:
                changed[key] = {"v": value}
            else:
                patch = diff(old[key], value)
                if patch is not None:
                    changed[key] = patch
        return {"d": changed, "x": [k for k in old if k not in new]}
    if isinstance(old, list) and isinstance(new, list):
        key = _row_key(old, new)
        if key is not None:
            return _diff_rows(old, new, key)
    return {"v": new}


def _diff_rows(old: list[Any], new: list[Any], key: str) -> dict[str, Any]:
    before = {r[key]: r for r in old}
    after = {r[key]: r for r in new}
    changed = {}
    for ident, row in after.items():
        change = {"v": row} if ident not in before else diff(before[ident], row)
        if change is not None:
            changed[ident] = change
    removed = [i for i in before if i not in after]
    patch: dict[str, Any] = {"l": changed, "k": key, "x": removed}
    if [i for i in before if i in after] == [i for i in after if i in before]:
        patch["i"] = [[index, i] for index, i in enumerate(after) if i not in before]
    else:
        patch["o"] = list(after)
    return patch


def apply(value: Any, patch: dict[str, Any]) -> Any:
    """`value` with `patch` applied (a new value; what the page does, in Python, for tests)."""
    if "v" in patch:
        return patch["v"]
    if "d" in patch:
        result = {k: v for k, v in value.items() if k not in patch["x"]}
        for key, sub in patch["d"].items():
            result[key] = apply(result.get(key), sub)
        return result
    key = patch["k"]
    rows = {r[key]: r for r in value}
    for ident in patch["x"]:
        rows.pop(ident, None)
    order = list(rows)
    for ident, sub in patch["l"].items():
        rows[ident] = apply(rows.get(ident), sub)
    if "o" in patch:
        order = patch["o"]
    else:
        for index, ident in patch["i"]:
            order.insert(index, ident)
    return [rows[i] for i in order]
