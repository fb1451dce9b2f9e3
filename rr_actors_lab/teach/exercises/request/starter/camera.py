"""The camera manager (you need not change it): one sensor, so one stream at a time.

A load opens the stream its request names; while it is open, a load of another
request raises (the sensor is busy). Equal requests share one stream: the registrar
loads it once for all of them (rule 1).
"""

from typing import Any

import rr_actors as rr


def setup(registrar: rr.ResourceRegistrar) -> None:
    """Register `stream`: a load opens the sensor for its request."""
    open_now: list[Any] = []  # the requests of the streams open (one, but while one closes)

    def open_stream(request: Any) -> dict[str, Any]:
        busy = [r for r in open_now if r != request]
        if busy:
            raise RuntimeError(f"camera busy: stream {busy[0]!r} is open, not {request!r}")
        open_now.append(request)
        return {"stream": request}

    def close_stream(request: Any, _response: Any) -> None:
        open_now.remove(request)

    registrar.register_server("stream", load=open_stream, unload=close_stream)
