"""Your copy of the registrar's in-doubt test (`rr-actors teach check` runs it in place
of the registrar's own, in every registrar of the simulated run).

A durable registrar writes each resource's row to its backup as it changes: `loading`
when a load starts, `loaded` when it is committed (its caller answered), `unloading`
when its unload starts; the row goes when the unload is done. A manager killed in the
middle of a load or an unload leaves a row that is neither. When the manager restarts,
the registrar asks this test of each row it restores: the rows in doubt are reported to
the manager (`registrar.in_doubt`) and settled (what they loaded is given back, their
dependencies released), so that nothing a crash cut short is leaked silently.
"""


def in_doubt(state: str) -> bool:
    """Whether a restored row was cut short by a crash.

    Args:
        state: the row's state in the backup: "loading", "loaded" or "unloading".

    Returns:
        True: in doubt (reported, settled); False: restored as it is.
    """
    # A load cut short answered nobody: the next call simply loads it again. Only an
    # unload cut short needs finishing.
    return state == "unloading"
