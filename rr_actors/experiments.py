"""Deprecated: `rr_actors_lab.experiments`, where this moved (issue 54); goes in the next release.

Each name of `rr_actors.experiments` is `rr_actors_lab.experiments`'s, with a `DeprecationWarning`
(`rr_actors._moved.alias`); the runtime itself never imports the lab.
"""

from rr_actors._moved import alias

__getattr__ = alias(__spec__.name)
