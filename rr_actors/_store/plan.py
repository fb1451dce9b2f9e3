"""What a write changes: the statements that bring the file from what the store last
wrote (its mirror) to the catalog's current rows.

```
 Changes (rid -> Resource | None, qid -> ClientRecord | None,
          rid -> the consumer ids added or released since the last write)
   --plan_resource / plan_client, against the mirror--> [(sql, params), ...] and the
   mirror entries to set once they committed (`GONE`: remove)
```

Only what differs reaches the file, addressed by row key (`seq`), and of a resource's
consumers only the ids `Changes.consumers` names: a change costs the same however large
the catalog or widely shared the resource. Values are pickled here, before anything is
written.
"""

from __future__ import annotations

from typing import Any

from rr_actors._catalog import NO_DIGEST, ClientRecord, Resource, request_digest
from rr_actors._store import codec
from rr_actors._store.codec import STATE_CODES
from rr_actors._store.restore import Mirror, Texts

Op = tuple[str, tuple[Any, ...]]  # one planned SQL statement and its parameters
GONE = object()  # a mirror entry to delete once a write committed


def plan_resource(
    written: dict[str, Mirror],
    ops: list[Op],
    mirrors: list[tuple[dict[str, Any], str, Any]],
    rid: str,
    resource: Resource | None,
    seq: int,
    touched: dict[str, None] | None = None,
) -> int:
    """Append to `ops` the statements for resource `rid` (`None`: removed), and to `mirrors`
    the `(table, key, value)` entries to set once they committed; the last row key.
    `touched`: the consumer ids to look at (`None`: every one)."""
    old = written.get(rid)
    if resource is None:
        if old is not None:
            ops.append(("DELETE FROM resources WHERE seq = ?", (old.seq,)))
            ops.append(("DELETE FROM consumers WHERE resource = ?", (old.seq,)))
            mirrors.append((written, rid, GONE))
        return seq
    texts = (resource.request_text, resource.response_text, resource.label)
    if old is None:
        seq += 1
        digest = resource.digest
        if digest is None:
            digest = request_digest(resource.request)
        ops.append(
            (
                "INSERT INTO resources (seq, id, server, state, digest, request, response, "
                "request_text, response_text, label, failed) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    seq,
                    rid,
                    resource.server,
                    STATE_CODES[resource.state],
                    None if digest == NO_DIGEST else digest,
                    codec.dumps(resource.request),
                    codec.dumps(resource.response),
                    *texts,
                    int(resource.failed),
                ),
            )
        )
        keys: dict[str, int] = {}
        row = seq
        touched = None
        update: Op | None = None
    else:
        update = None
        if (
            old.response_version != resource.response_version
            or old.state is not resource.state
            or old.texts != texts
            or old.failed != resource.failed
        ):
            update = _resource_update(old, resource, texts)
            ops.append(update)
        keys = old.consumers
        row = old.seq
    now = resource.consumers
    if touched is None:  # every consumer, against the mirror
        touched = {**dict.fromkeys(now), **dict.fromkeys(keys)}
    for query_id in touched:  # one INSERT or DELETE each whose row differs from `now`
        key = keys.get(query_id)
        if query_id in now:
            if key is None:
                seq += 1
                ops.append(
                    (
                        "INSERT INTO consumers (resource, seq, query_id, origin_rr) "
                        "VALUES (?, ?, ?, ?)",
                        (row, seq, query_id, now[query_id]),
                    )
                )
                mirrors.append((keys, query_id, seq))
        elif key is not None:
            ops.append(("DELETE FROM consumers WHERE resource = ? AND seq = ?", (row, key)))
            mirrors.append((keys, query_id, GONE))
    if old is None or update is not None:
        # (the consumer keys stay in `keys`, the one dict: changed in place once committed)
        mirror = Mirror(
            row, resource.state, resource.response_version, keys, texts, resource.failed
        )
        mirrors.append((written, rid, mirror))
    return seq


def _resource_update(old: Mirror, resource: Resource, texts: Texts) -> Op:
    """The one `UPDATE` that brings a written resource row up to date."""
    columns: list[str] = []
    values: list[Any] = []
    if old.response_version != resource.response_version:
        columns += ["state", "response"]
        values += [STATE_CODES[resource.state], codec.dumps(resource.response)]
    elif old.state is not resource.state:
        columns.append("state")
        values.append(STATE_CODES[resource.state])
    if old.texts != texts:
        columns += ["request_text", "response_text", "label"]
        values += texts
    if old.failed != resource.failed:
        columns.append("failed")
        values.append(int(resource.failed))
    assignments = ", ".join(f"{column} = ?" for column in columns)
    sql = f"UPDATE resources SET {assignments} WHERE seq = ?"  # noqa: S608 - our column names
    return (sql, (*values, old.seq))


def plan_client(
    written: dict[str, tuple[int, int, str | None]],
    ops: list[Op],
    mirrors: list[tuple[dict[str, Any], str, Any]],
    qid: str,
    record: ClientRecord | None,
    seq: int,
) -> int:
    """Plan the statements for client record `qid` (`None`: removed), as `plan_resource`
    (`written`: query id -> `(row key, response_version, request_text)`)."""
    old = written.get(qid)
    if record is None:
        if old is not None:
            ops.append(("DELETE FROM clients WHERE seq = ?", (old[0],)))
            mirrors.append((written, qid, GONE))
        return seq
    query = record.query
    if old is None:
        seq += 1
        row = seq
        ops.append(
            (
                "INSERT INTO clients (seq, query_id, server, serving_rr, origin_rr, request, "
                "response, parent, loaded, request_text) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    seq,
                    qid,
                    query.server,
                    query.serving_rr,
                    query.origin_rr,
                    codec.dumps(query.request),
                    codec.dumps(query.response),
                    record.parent,
                    int(record.loaded),
                    record.request_text,
                ),
            )
        )
    elif old[1] == record.response_version:
        row = old[0]
        ops.append(
            (
                "UPDATE clients SET loaded = ?, request_text = ? WHERE seq = ?",
                (int(record.loaded), record.request_text, row),
            )
        )
    else:
        row = old[0]
        ops.append(
            (
                "UPDATE clients SET response = ?, loaded = ?, request_text = ? WHERE seq = ?",
                (codec.dumps(query.response), int(record.loaded), record.request_text, row),
            )
        )
    mirrors.append((written, qid, (row, record.response_version, record.request_text)))
    return seq
