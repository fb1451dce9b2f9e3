"""The Zenoh carrier (extra `zenoh`): registrars across hosts over Eclipse Zenoh.

The link: `net` (`ZenohNetwork`: a router per host, the session it opens, one system per
process), `carrier` (`ZenohCarrier`: the messenger's carrier: routes, serving, answers),
`link` (frames both ways: outboxes and the inbox), `presence` (who serves what, from
liveliness tokens: the carrier's reports), `wire` (the key expressions and the header),
`callbacks` (Zenoh's callback threads, and rr_actors' threads that call Zenoh, ended
before the interpreter finalizes).
The operations, apart: `ops/` (TLS, the access control, the gate). What runs beside a
session (the events across hosts, the link watch) is the observer's (`net.Beside`), the
command line's options `rr_actors._tools.options`. Nothing here imports `zenoh` at the
package's import: only its modules do.
"""
