"""The actions manager: two servers, `look` and `follow`, both using the camera.

`setup` runs in the manager each time it starts (and again after each restart).
"""

from typing import Any

import rr_actors as rr


def setup(registrar: rr.ResourceRegistrar) -> None:
    """Register the two actions; each needs the camera's front stream."""
    # Open the camera once, when the manager starts, and share it between the actions.
    camera = registrar.call("camera", "resource", "front")

    def look(request: Any) -> dict[str, Any]:
        return {"looking at": request, "stream": camera.response}

    def follow(request: Any) -> dict[str, Any]:
        return {"following": request, "stream": camera.response}

    def nothing(_request: Any, _response: Any) -> None:
        pass

    registrar.register_server("look", load=look, unload=nothing)
    registrar.register_server("follow", load=follow, unload=nothing)
