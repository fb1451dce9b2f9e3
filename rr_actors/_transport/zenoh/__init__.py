"""The Zenoh carrier (extra `zenoh`): registrars across hosts over Eclipse Zenoh.

`net` (`ZenohNetwork`, a router per host), `carrier` (`ZenohMember`: a process's
membership), `outbox`, `inbox`, `presence`, `queue`, `wire` (the key expressions and the
header), and who may cross hosts: `tls` (`ZenohTLS`), `config`, `watch`, `probe`, `gate`,
`access`. Nothing here imports `zenoh` at the package's import: only its modules do.
"""
