"""The generic actor machinery: knows nothing of registrars, catalogs or processes.

- `runtime`: the seam every thread, lock, event, queue, clock, id and random value goes
  through: the stdlib's own objects, or a simulation's (`rr_actors.simulation`).
- `actor`: pykka's threading actor with a one-lock mailbox and one-shot futures; every
  pykka extension point (and every private name of pykka) rr_actors uses is in that file.
- `replies`: where the answer to a message goes (`Reply` objects), and how to wait.
- `workers`: the pool of threads that runs user callbacks off the mailboxes.
- `serial`: `SerialExecutor`, the one queue-and-thread: tasks in order on a thread of
  their own, the submitter never blocked (the carriers, a supervisor, the event queues).
- `bus` and `queues`: events published to subscriptions and forwarders that never slow
  the publisher (and `LateQueue`); `wire`: what a message offers to cross processes.
- `directory`: names -> peers (`Peer.tell`), and why a name went away.
- `timers`: one-shot timers with an injectable factory.
"""
