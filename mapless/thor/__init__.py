"""Live AI2-THOR backend (optional extra ``mapless[thor]``; ``ai2thor`` is imported lazily)."""

from mapless.thor.backend import (
    LiveThorScene,
    ObjectTable,
    ThorConfig,
    make_controller,
    observation_from_event,
    scrape,
    scrape_scene,
)

__all__ = [
    "LiveThorScene",
    "ObjectTable",
    "ThorConfig",
    "make_controller",
    "observation_from_event",
    "scrape",
    "scrape_scene",
]
