"""The camera manager: camera streams, and a recalibration that warns their users.

`setup` runs in the manager each time it starts (and again after each restart).
"""

from typing import Any

import rr_actors as rr


def setup(registrar: rr.ResourceRegistrar) -> None:
    """Register `stream` (a load opens a stream) and `recalibrate` (a load recalibrates
    the camera: every stream open is disturbed for a while)."""

    def open_stream(request: Any) -> dict[str, Any]:
        return {"stream": request}

    def close_stream(_request: Any, _response: Any) -> None:
        pass

    def recalibrate(request: Any) -> dict[str, Any]:
        # send_status tells every consumer of the resource: one status is enough.
        held = registrar.server_queries("stream")
        if held:
            registrar.send_status(held[0].id, rr.Status.WARNING, "recalibrating")
        return {"recalibrated": request}

    registrar.register_server("stream", load=open_stream, unload=close_stream)
    registrar.register_server("recalibrate", load=recalibrate, unload=close_stream)
