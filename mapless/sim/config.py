"""Parameters of the geometric simulator. Every field enters the cache hash (sim/cache.py)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from mapless.errors import MaplessError

#: AI2-THOR's default agent stands with its capsule centre at y = 0.901 and carries the camera
#: 0.675 m above it (the agent prefab's camera offset), so the eye is at about 1.576 m.
DEFAULT_EYE_HEIGHT = 1.576


@dataclass(frozen=True)
class SimConfig:
    """Camera, action and visibility parameters.

    ``ray_resolution`` is the side of the square ray grid cast per pose (each ray stands for
    ``300 / ray_resolution`` pixels of the 300x300 frame); it must be a multiple of 7 so the
    feature map pools evenly.
    """

    image_size: int = 300
    horizontal_fov: float = 90.0
    eye_height: float = DEFAULT_EYE_HEIGHT
    horizons: tuple[int, ...] = (0, 30)
    rotation_step: int = 45
    grid_size: float = 0.25
    visibility_distance: float = 1.0
    ray_resolution: int = 84
    category_set: str = "mjolnir101"
    #: Obstacle footprints are shrunk by this margin before testing a move's segment (the
    #: reachable grid was filtered with the same margin): exactly on square footprints, less on the
    #: long sides of elongated ones (:func:`mapless.sim.room.obstacle_polygons`).
    obstacle_margin: float = 0.1
    #: Distance from the reachable grid that still counts as room interior when walls are built.
    wall_clearance: float = 0.45
    #: A diagonal MoveAhead also needs both orthogonal neighbours it passes between on the grid (off:
    #: SAVN's offline rule, which lets 6.3 % of diagonal steps cut past a wall corner; real
    #: AI2-THOR's 45° step would stop there). docs/guide/simulator.md, "Diagonal moves".
    strict_diagonals: bool = False

    def __post_init__(self) -> None:
        # MoveAhead steps to a neighbour on the 0.25 m grid of the built-in scenes' reachable
        # positions, straight or diagonal: other grids, and headings between the eight directions,
        # have no neighbour to step to.
        checks = {
            "image_size": (self.image_size > 0, "must be > 0"),
            "horizontal_fov": (0 < self.horizontal_fov < 180, "must be in (0, 180)"),
            "eye_height": (self.eye_height > 0, "must be > 0"),
            "horizons": (
                len(self.horizons) > 0 and all(-90 < h < 90 for h in self.horizons),
                "must be a non-empty list of angles in (-90, 90)",
            ),
            "rotation_step": (
                self.rotation_step in (45, 90, 180),
                "must be 45, 90 or 180 (MoveAhead steps to one of the eight grid neighbours)",
            ),
            "grid_size": (
                self.grid_size == 0.25,
                "must be 0.25 (the grid of the scenes' reachable positions)",
            ),
            "visibility_distance": (self.visibility_distance > 0, "must be > 0"),
            "strict_diagonals": (isinstance(self.strict_diagonals, bool), "must be true or false"),
            "ray_resolution": (
                self.ray_resolution > 0 and self.ray_resolution % 7 == 0,
                "must be a positive multiple of 7 (the 7x7 feature map)",
            ),
        }
        for key, (ok, requirement) in checks.items():
            if not ok:
                raise MaplessError(
                    f"invalid simulator setting sim.{key} = {getattr(self, key)!r}: {requirement}"
                )
        object.__setattr__(self, "horizons", tuple(sorted(int(h) for h in self.horizons)))

    @property
    def yaws(self) -> tuple[int, ...]:
        return tuple(range(0, 360, self.rotation_step))

    def as_dict(self) -> dict:
        return asdict(self)
