"""The actions manager: two servers, `look` and `follow`, both using the camera.

`setup` runs in the manager each time it starts (and again after each restart).
"""

from typing import Any

import rr_actors as rr


def setup(registrar: rr.ResourceRegistrar) -> None:
    """Register the two actions; each needs the camera's front stream."""

    # Each load calls the camera itself: a call made while loading is a dependency of the
    # resource loaded, released with it (rule 7). Both actions ask for the same request,
    # so the camera serves one stream to both (equal requests share one resource).
    def look(request: Any) -> dict[str, Any]:
        camera = registrar.call("camera", "resource", "front")
        return {"looking at": request, "stream": camera.response}

    def follow(request: Any) -> dict[str, Any]:
        camera = registrar.call("camera", "resource", "front")
        return {"following": request, "stream": camera.response}

    def nothing(_request: Any, _response: Any) -> None:
        pass

    registrar.register_server("look", load=look, unload=nothing)
    registrar.register_server("follow", load=follow, unload=nothing)
