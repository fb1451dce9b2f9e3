"""The generic actor machinery: knows nothing of registrars, catalogs or processes.

`runtime` (the seam every thread, clock and id goes through), `actor` (pykka's actor with a
one-lock mailbox), `replies`, `loops`, `workers`, `serial`, `bus` and `queues` (events that
never slow the publisher), `wire`, `directory`, `membership`, `hlc`, `traces`, `exit`.
"""
