"""Reading a plan's `[workload]`: the clients, their pace, and the calls they mix.

Part of `reading._Reader`; every problem is a `PlanError` with its line (`_checks`).
"""

from __future__ import annotations

import string
from typing import Any

from rr_actors.experiments._checks import Checks
from rr_actors.experiments._lines import KeyPath
from rr_actors.experiments.plan import (
    MAX_SECONDS,
    PLACEHOLDERS,
    CallMix,
    ManagerPlan,
    Workload,
    is_number,
)

__all__ = ["WorkloadChecks"]


class WorkloadChecks(Checks):
    """Reads `[workload]` and its `[[workload.calls]]` (their request templates too)."""

    def workload(self, value: Any, managers: dict[str, ManagerPlan]) -> Workload:
        path: KeyPath = ("workload",)
        table = self.table(value, path, ("clients", "rate", "arrivals", "hold", "timeout", "calls"))
        clients = self.integer(table, path, "clients", 1, low=0)
        rate: Any = table.get("rate", 5.0)
        if rate == "max":
            rate = None
        elif not is_number(rate) or rate < 1 / MAX_SECONDS:
            raise self.error(
                (*path, "rate"),
                f'must be calls per second (at least {1 / MAX_SECONDS:g}) or "max", got {rate!r}',
            )
        calls_data = table.get("calls", [])
        if not isinstance(calls_data, list):
            raise self.error((*path, "calls"), "must be an array of tables ([[workload.calls]])")
        if clients and not calls_data:
            raise self.error(path, "'calls' is missing: what do the clients call?")
        calls = tuple(
            self.call(entry, (*path, "calls", index), managers)
            for index, entry in enumerate(calls_data)
        )
        return Workload(
            clients=clients,
            rate=None if rate is None else float(rate),
            arrivals=self.choice(table, path, "arrivals", "poisson", ("poisson", "fixed")),
            hold=self.seconds(table, path, "hold", 0.5, zero=True),
            timeout=self.seconds(table, path, "timeout", 5.0),
            calls=calls,
        )

    def call(self, value: Any, path: KeyPath, managers: dict[str, ManagerPlan]) -> CallMix:
        table = self.table(
            value, path, ("manager", "server", "weight", "shared", "keys", "request", "factory")
        )
        manager = self.required(table, path, "manager")
        if not isinstance(manager, str):
            raise self.error((*path, "manager"), f"must be a manager's name, got {manager!r}")
        if manager not in managers:
            raise self.error(
                (*path, "manager"),
                f"no manager {manager!r} in the tree (managers: {', '.join(managers)})",
            )
        server = self.required(table, path, "server")
        if not isinstance(server, str) or not server:
            raise self.error((*path, "server"), f"must be a server name, got {server!r}")
        weight = table.get("weight", 1.0)
        if not is_number(weight) or weight <= 0:
            raise self.error((*path, "weight"), f"must be a positive number, got {weight!r}")
        shared = table.get("shared", 0.5)
        if not is_number(shared) or not 0 <= shared <= 1:
            raise self.error((*path, "shared"), f"must be a fraction from 0 to 1, got {shared!r}")
        if "request" in table and "factory" in table:
            raise self.error((*path, "factory"), "give either 'request' or 'factory', not both")
        factory = self.text(table, path, "factory", None)
        if factory is not None:
            function = self.importable((*path, "factory"), factory)
            self.signature_takes((*path, "factory"), function, factory, ("key", None), {})
        request = table.get("request", "{key}")
        self.template(request, (*path, "request"))
        return CallMix(
            manager=manager,
            server=server,
            weight=float(weight),
            shared=float(shared),
            keys=self.integer(table, path, "keys", 4, low=1),
            request=request,
            factory=factory,
        )

    def template(self, value: Any, path: KeyPath) -> None:
        """Check the placeholders of every string in a request template.

        A placeholder is only a name: `{key}`, not `{key!r}` or `{client:03d}`. With no
        conversion, format spec, attribute or index, every template renders at run time
        for any key and client, so a template that passes here cannot fail in a client.
        """
        if isinstance(value, dict):
            for key, item in value.items():
                self.template(item, (*path, key))
        elif isinstance(value, list):
            for index, item in enumerate(value):
                self.template(item, (*path, index))
        elif isinstance(value, str):
            try:
                parsed = [p for p in string.Formatter().parse(value) if p[1] is not None]
            except ValueError as exc:
                raise self.error(path, f"{value!r} is not a valid template: {exc}") from None
            for _, field, spec, conversion in parsed:
                if spec or conversion:
                    raise self.error(
                        path,
                        f"{value!r}: a placeholder is only a name, like {{{field}}}, without "
                        "a conversion ('!r') or a format ('03d')",
                    )
            fields = [field for _, field, _, _ in parsed]
            unknown = [f for f in fields if f not in PLACEHOLDERS]
            if unknown:
                raise self.error(
                    path,
                    f"unknown placeholder {{{unknown[0]}}}; known: "
                    + ", ".join(f"{{{p}}}" for p in sorted(PLACEHOLDERS)),
                )
