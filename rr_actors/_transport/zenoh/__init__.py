"""The Zenoh carrier (extra `zenoh`): registrars across hosts over Eclipse Zenoh.

`net` (`ZenohNetwork`, a router per host), `carrier` (`ZenohMember`: a process's
membership), `outbox`, `inbox`, `presence`, `wire` (the key expressions and the header),
`events` (every host's events as JSON lines), `options` (the command line's network
options), and who may cross hosts: `tls` (`ZenohTLS`), `config`, `watch`, `probe`,
`gate`, `access`. Nothing here imports `zenoh` at the package's import: only its modules do.
"""
