"""The actions manager (yours): two servers, `look` and `follow`, each using the camera.

`setup` runs in the manager each time it starts (and again after each restart).
"""

from typing import Any

import rr_actors as rr

FRONT = {"view": "front"}
"""The camera's request: what tells its streams apart, and nothing else (rule 1: equal
requests share one stream, so every action asks for this one)."""


def setup(registrar: rr.ResourceRegistrar) -> None:
    """Register the two actions; each loads the camera's front stream as it loads."""

    def look(request: Any) -> dict[str, Any]:
        camera = registrar.call("camera", "stream", FRONT)
        return {"looking at": request, "stream": camera.response}

    def follow(request: Any) -> dict[str, Any]:
        camera = registrar.call("camera", "stream", FRONT)
        return {"following": request, "stream": camera.response}

    def nothing(_request: Any, _response: Any) -> None:
        pass

    registrar.register_server("look", load=look, unload=nothing)
    registrar.register_server("follow", load=follow, unload=nothing)
