"""The AF_UNIX carrier: the registrars of one machine, over authenticated Unix sockets.

`system` (`System`, `attach`, who is lost: rule 19), `link` (the connections both ways).
"""
