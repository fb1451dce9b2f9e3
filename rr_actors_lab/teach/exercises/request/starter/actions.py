"""The actions manager (yours): two servers, `look` and `follow`, each using the camera.

`setup` runs in the manager each time it starts (and again after each restart).
"""

from typing import Any

import rr_actors as rr


def setup(registrar: rr.ResourceRegistrar) -> None:
    """Register the two actions; each loads the camera's front stream as it loads."""

    def look(request: Any) -> dict[str, Any]:
        # Tell the camera who asks: it helps when reading its logs.
        camera = registrar.call("camera", "stream", {"view": "front", "for": f"look {request}"})
        return {"looking at": request, "stream": camera.response}

    def follow(request: Any) -> dict[str, Any]:
        camera = registrar.call("camera", "stream", {"view": "front", "for": f"follow {request}"})
        return {"following": request, "stream": camera.response}

    def nothing(_request: Any, _response: Any) -> None:
        pass

    registrar.register_server("look", load=look, unload=nothing)
    registrar.register_server("follow", load=follow, unload=nothing)
