"""The cut exercise's rule 22 policy: which of two registrars of one name is kept."""

from rr_actors import Claimant


def keep(first: Claimant, second: Claimant) -> Claimant:
    """Keep the registrar that began to serve on a side with a majority of the members."""
    return first if first.majority else second
