"""Registrar configuration (TeMoto's `Configuration`, thesis table 4.2)."""

from __future__ import annotations

import dataclasses
import math
import os
import re
from typing import Any, Literal

from rr_actors.errors import ConfigError

__all__ = ["RegistrarConfig"]

_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")

Durability = Literal["process", "power"]


def _check_duration(field: str, value: object, *, allow_none: bool) -> None:
    """Raise `ConfigError` naming `field` unless `value` is a finite, positive float or int."""
    if value is None and allow_none:
        return
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or value <= 0
    ):
        raise ConfigError(f"{field} must be a positive number of seconds, got {value!r}")


@dataclasses.dataclass(frozen=True)
class RegistrarConfig:
    """How a [`ResourceRegistrar`][rr_actors.ResourceRegistrar] behaves.

    Validated at construction; change a copy with `dataclasses.replace`.

    Attributes:
        name: registrar name, unique within its system; letters, digits, `_`, `-`, `.`.
        backup_path: SQLite file that keeps the catalog, or `None` for an in-memory catalog.
        save_interval: with a backup, flush changes every this many seconds (`None`: never
            on a timer). A crash loses at most one interval of changes.
        save_on_modify: with a backup, make every load and unload durable before its
            caller gets the answer.
        erase_on_destruct: remove the backup after a clean `stop()` (a crash always keeps it).
        call_timeout: default `timeout` of every blocking call, in seconds.
        durability: `"process"` survives a crash of the process (SQLite `synchronous=NORMAL`),
            `"power"` also survives power loss (`synchronous=FULL`, slower).

    Raises:
        ConfigError: a field is invalid; the message names it.
    """

    name: str = "untitled"
    backup_path: str | os.PathLike[str] | None = None
    save_interval: float | None = 60.0
    save_on_modify: bool = False
    erase_on_destruct: bool = False
    call_timeout: float = 10.0
    durability: Durability = "process"

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not _NAME.match(self.name):
            raise ConfigError(
                f"name must be a non-empty string of letters, digits, '_', '-' or '.', "
                f"got {self.name!r}"
            )
        if self.backup_path is not None and not isinstance(self.backup_path, str | os.PathLike):
            raise ConfigError(f"backup_path must be a path or None, got {self.backup_path!r}")
        _check_duration("save_interval", self.save_interval, allow_none=True)
        _check_duration("call_timeout", self.call_timeout, allow_none=False)
        for flag in ("save_on_modify", "erase_on_destruct"):
            if not isinstance(getattr(self, flag), bool):
                raise ConfigError(f"{flag} must be a bool, got {getattr(self, flag)!r}")
        if self.durability not in ("process", "power"):
            raise ConfigError(f"durability must be 'process' or 'power', got {self.durability!r}")

    def to_dict(self) -> dict[str, Any]:
        """Return the configuration as plain JSON-able data (with a schema version)."""
        data = dataclasses.asdict(self)
        data["backup_path"] = None if self.backup_path is None else os.fspath(self.backup_path)
        data["schema"] = 1
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RegistrarConfig:
        """Build a configuration from [`to_dict`][rr_actors.RegistrarConfig.to_dict] output.

        Raises:
            ConfigError: unknown schema version, unknown field, or an invalid value.
        """
        if data.get("schema") != 1:
            raise ConfigError(f"unsupported RegistrarConfig schema {data.get('schema')!r}")
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - fields - {"schema"}
        if unknown:
            raise ConfigError(f"unknown RegistrarConfig fields: {sorted(unknown)}")
        return cls(**{k: v for k, v in data.items() if k in fields})
