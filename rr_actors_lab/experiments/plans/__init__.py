"""The plans shipped with rr_actors, runnable by name: `rr-actors experiment first --out DIR`.

Each is a commented example of the plan format; `plan-reference.md` beside them is the
format's reference (the documentation's `reference/plan.md`).
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["REFERENCE", "find", "shipped"]

HERE = Path(__file__).resolve().parent

REFERENCE = HERE / "plan-reference.md"
"""The plan format's reference, as shipped."""


def shipped() -> dict[str, Path]:
    """The shipped plans by name (the file's stem), sorted by name."""
    return {path.stem: path for path in sorted(HERE.glob("*.toml"))}


def find(plan: str) -> Path:
    """The plan file `plan` names (a path, or a shipped plan's name with or without `.toml`);
    anything else comes back as it is (reading it then says it cannot be read)."""
    path = Path(plan)
    if path.exists() or path.parent != Path():
        return path
    return shipped().get(path.name.removesuffix(".toml"), path)
