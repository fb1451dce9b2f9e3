"""Operator tooling behind the command line, apart from the carriers it serves.

`certs`: `rr-actors certs init` / `issue` (a system's CA, a host's certificate);
`options`: the options of the commands that join a system over Zenoh (`--network`, ...).
"""
