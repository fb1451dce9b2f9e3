"""The Zenoh carrier's operations: who may cross hosts (TLS, the access control, the gate).

`tls` (`ZenohTLS`), `config` (a session's config), `access` (who else may read a private
file), `gate` (a flood's gate on a `tls/` port). None of it moves a registrar's message.
"""
