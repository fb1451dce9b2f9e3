"""The Zenoh carrier (extra `zenoh`): registrars across hosts over Eclipse Zenoh.

`net` (`ZenohNetwork`), `carrier` (the messenger's carrier), `link` (outboxes and inbox),
`presence` (who serves what, from liveliness tokens), `wire` (keys and header),
`callbacks` (Zenoh's threads ended before the interpreter finalizes); `ops/` who may
cross hosts. What runs beside a session is the observer's (`net.Beside`).
"""
