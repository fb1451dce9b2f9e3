"""Operator tooling behind the command line, apart from the carriers it serves.

`certs`: `rr-actors certs init` / `issue` (a system's CA, a host's certificate);
`files`: a file a command reads from a folder it was given, within bounds (a plan, a run's
`seeds.jsonl`, an exercise's `.teach.json`); `options`: the options of the commands that
join a system over Zenoh (`--network`, ...).
"""
