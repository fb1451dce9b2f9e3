"""The observer tests' supervision tree: the TeMoto thesis's figure 2.7.

Its own module, importing nothing of pytest: a manager process unpickles these setups by
reference, so it imports this module when it (re)starts, and every millisecond of that
import is a millisecond of every restart the tests measure.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import rr_actors as rr

__all__ = ["REQUEST", "cm_setup", "device", "erm_setup", "figure_27"]


def device(request: Any) -> dict[str, Any]:
    """The camera's response (what its load returns)."""
    return {"device": request}


def erm_setup(registrar: rr.ResourceRegistrar, camera: Callable[[Any], Any] | None = None) -> None:
    """The external resource manager: a camera and a filter (stand-ins for processes).

    `camera`: the camera's load (a test holds it at a gate), else `device`.
    """
    registrar.register_server("camera", load=camera or device, unload=lambda q, r: None)
    registrar.register_server("filter", load=lambda r: {"filter": r}, unload=lambda q, r: None)


def cm_setup(registrar: rr.ResourceRegistrar) -> None:
    """The component manager: a filtered camera made of the ERM's camera and filter."""

    def load(request: dict[str, str]) -> dict[str, Any]:
        camera = registrar.call("erm", "camera", request["device"])
        filtered = registrar.call("erm", "filter", request["filter"])
        return {"camera": camera.response, "filter": filtered.response}

    registrar.register_server("filtered_camera", load=load, unload=lambda q, r: None)


REQUEST = {"device": "/dev/video0", "filter": "blur"}


def figure_27(
    make: Callable[..., rr.Supervisor],
    isolation: str = "process",
    *,
    camera: Callable[[Any], Any] | None = None,
    **kwargs: Any,
) -> rr.Supervisor:
    """A supervisor of the ERM and the CM (not started); `camera`: the camera's load."""
    erm = erm_setup if camera is None else functools.partial(erm_setup, camera=camera)
    return make(
        [
            rr.ManagerSpec("erm", erm, isolation=isolation),  # type: ignore[arg-type]
            rr.ManagerSpec("cm", cm_setup, isolation=isolation),  # type: ignore[arg-type]
        ],
        **kwargs,
    )
