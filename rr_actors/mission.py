"""Deprecated: `rr_actors_lab.mission`, where this moved (issue 54); goes in the next release.

Each name of `rr_actors.mission` is `rr_actors_lab.mission`'s, with a `DeprecationWarning`
(`rr_actors._moved.alias`); the runtime itself never imports the lab.
"""

from rr_actors._moved import alias

__getattr__ = alias(__spec__.name)

if __name__ == "__main__":  # `python -m rr_actors.mission`: the demo, from its new home
    import runpy

    from rr_actors._moved import warn

    warn("python -m rr_actors.mission", "python -m rr_actors_lab.mission", stacklevel=2)
    runpy.run_module("rr_actors_lab.mission", run_name="__main__", alter_sys=True)
