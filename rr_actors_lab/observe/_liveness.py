"""Which hosts are live, and how each pair of them is linked, from what each host shares.

```
 SystemView ── mirrors (one Mirror a host: its token here?, its state synced?, sections)
      │
      └─► Liveness.hosts() ─► "hosts": each host live, joining (token, no state yet) or
      │                        stale (no token: since when, and why)
      └─► Liveness.links() ─► "links": each pair of hosts up or down, since when, why
      └─► Liveness.why(member): a stale host's cause (ended, a cut link, its token went)
```

Runs on the `SystemView`'s executor thread, where the mirrors change.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from rr_actors_lab.observe._crossing import link_row

if TYPE_CHECKING:
    from rr_actors._transport.zenoh.net import Services

__all__ = ["Liveness", "Mirror"]


@dataclasses.dataclass
class Mirror:
    """What a page's host knows of one host's state."""

    member: str
    instance: str | None = None
    seq: int = 0
    last_event: int = 0
    sections: dict[str, Any] = dataclasses.field(default_factory=dict)
    published: set[str] = dataclasses.field(default_factory=set)
    here: bool = False  # its token is there
    synced: bool = False  # its state arrived since it came (back)
    behind: bool = False  # a delta was missed: its state is asked again (shown meanwhile)
    newest: tuple[str, int] = ("", 0)  # the newest delta seen: (instance, seq)
    since: float = dataclasses.field(default_factory=time.time)
    why: str = ""
    asked: float = -math.inf  # monotonic: when its state was last asked


class Liveness:
    """The `hosts` and `links` sections of a page across hosts.

    Args:
        member: this host's member name (`None`: it shares nothing, only shows).
        services: the router's session and what goes with it (this host's links, the
            lease).
        mirrors: what the page's host knows of each host (read only; the `SystemView`
            keeps it).
    """

    def __init__(
        self, member: str | None, services: Services, mirrors: Mapping[str, Mirror]
    ) -> None:
        self.member = member
        self._services = services
        self._mirrors = mirrors

    def report(self, reporter: str, about: str) -> dict[str, Any] | None:
        """What `reporter` last said of its link to `about` (its own links are fresh)."""
        if reporter == self.member:  # (this host's own: from its link watch, now)
            links = [link_row(m) for m in self._services.links()]
        else:
            mirror = self._mirrors.get(reporter)
            if mirror is None or not (mirror.here and mirror.synced):
                return None
            links = mirror.sections.get("links") or []
        return next((link for link in links if link["member"] == about), None)

    def why(self, member: str) -> str:
        """Why host `member` is stale (its token went), as the page says it."""
        mirror = self._mirrors.get(member)
        if mirror is not None and mirror.sections.get("ended"):
            return "its supervisor stopped"  # (it shared its final state first)
        own = self.report(self.member, member) if self.member else None
        if own is not None and not own["up"]:
            return str(own["why"])
        lease = self._services.lease
        return (
            f"its observer's token went: it stopped sharing, or nothing was heard from it "
            f"within the lease ({lease:g} s)"
        )

    def hosts(self) -> dict[str, Any]:
        """The `hosts` section: this host first, each live, joining or stale."""
        hosts = []
        for member in self._members():
            mirror = self._mirrors[member]
            info = mirror.sections.get("host") or {}
            if mirror.here and mirror.synced:
                state = "live"
            elif mirror.here:
                state = "joining"
            else:
                state = "stale"
            hosts.append(
                {
                    "member": member,
                    "state": state,
                    "since": mirror.since,
                    "why": mirror.why,
                    "allow_faults": bool(info.get("allow_faults", False)) and state == "live",
                    "title": info.get("title", ""),
                    "pid": info.get("pid"),
                    "here": member == self.member,
                }
            )
        return {"self": self.member, "lease": self._services.lease, "hosts": hosts}

    def _members(self) -> list[str]:
        members = sorted(self._mirrors)
        if self.member is not None and self.member in self._mirrors:  # this host first
            members.remove(self.member)
            members.insert(0, self.member)
        return members

    def links(self) -> list[dict[str, Any]]:
        """The `links` section: each pair of hosts, up or down, since when, why."""
        members = set(self._mirrors)
        if self.member is not None:
            members.add(self.member)
        pairs = []
        for a in sorted(members):
            for b in sorted(members):
                if a >= b:
                    continue
                pairs.append(self._pair(a, b))
        return pairs

    def _pair(self, a: str, b: str) -> dict[str, Any]:
        reports = [(r, self.report(x, y)) for r, (x, y) in ((a, (a, b)), (b, (b, a)))]
        down = [(who, r) for who, r in reports if r is not None and not r["up"]]
        up = [(who, r) for who, r in reports if r is not None and r["up"]]
        pair: dict[str, Any] = {"id": f"{a}|{b}", "a": a, "b": b}
        if down:
            who, report = min(down, key=lambda d: d[1]["since"])
            return {**pair, "up": False, "since": report["since"], "why": f"{who}: {report['why']}"}
        if up:
            return {**pair, "up": True, "since": max(r["since"] for _, r in up), "why": ""}
        gone = [
            self._mirrors[m] for m in (a, b) if m in self._mirrors and not self._mirrors[m].here
        ]
        if gone:
            return {**pair, "up": False, "since": gone[0].since, "why": gone[0].why}
        return {**pair, "up": True, "since": None, "why": ""}
