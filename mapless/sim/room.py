"""Room boundary (walls) and floor obstacles, approximated from the layout.

The layout data has no walls. The room interior is taken as the floor's bounding box intersected
with the union of (a) the reachable grid dilated by ``wall_clearance`` (square element) and (b) the footprints of all
objects (furniture stands against walls, so walls lie just behind it). Walls are the boundary of
that interior, infinitely tall. For ray casting, the horizontal distance to the wall is tabulated
per reachable position and azimuth (0.5 degree steps, 2 cm marching).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from mapless.scenes.floor_plans import Scene

CELL = 0.02  # m, resolution of the interior mask
AZIMUTH_STEP = 0.5  # degrees
MAX_RANGE = 20.0  # m

#: Types that never block motion although they stand on the floor or span it (as the reachable-grid
#: filter of the shared data; their boxes are wall-mounted or hollow, or L-shaped and misleading).
NON_OBSTACLE_TYPES = frozenset(
    [
        "BathtubBasin",
        "Blinds",
        "Cabinet",
        "CounterTop",
        "Curtains",
        "Drawer",
        "Faucet",
        "Floor",
        "HandTowelHolder",
        "LightSwitch",
        "Mirror",
        "Painting",
        "Poster",
        "Shelf",
        "ShowerCurtain",
        "ShowerDoor",
        "ShowerGlass",
        "ShowerHead",
        "Sink",
        "SinkBasin",
        "StoveKnob",
        "ToiletPaperHanger",
        "TowelHolder",
        "Window",
    ]
)


class InteriorMask:
    """Boolean grid of the room interior on the xz plane."""

    def __init__(self, scene: Scene, wall_clearance: float):
        cx, _, cz = scene.floor_center
        sx, _, sz = scene.floor_size
        self.x0, self.z0 = cx - sx / 2, cz - sz / 2
        self.nx, self.nz = int(np.ceil(sx / CELL)) + 1, int(np.ceil(sz / CELL)) + 1
        mask = np.zeros((self.nx, self.nz), dtype=bool)
        ix, iz = self.cell_of(scene.reachable[:, 0], scene.reachable[:, 1])
        mask[np.clip(ix, 0, self.nx - 1), np.clip(iz, 0, self.nz - 1)] = True
        # A square structuring element keeps walls straight and axis-aligned, as iTHOR rooms are.
        side = 2 * round(wall_clearance / CELL) + 1
        mask = ndimage.binary_dilation(mask, structure=np.ones((side, side), dtype=bool))
        for obj in scene.objects:
            (x1, _, z1), (x2, _, z2) = obj.box_min, obj.box_max
            (i1, i2), (k1, k2) = self.cell_of(np.array([x1, x2]), np.array([z1, z2]))
            mask[max(i1, 0) : max(i2 + 1, 0), max(k1, 0) : max(k2 + 1, 0)] = True
        self.mask = mask

    def cell_of(self, x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.floor((x - self.x0) / CELL).astype(int), np.floor((z - self.z0) / CELL).astype(int)

    def inside(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        ix, iz = self.cell_of(x, z)
        ok = (ix >= 0) & (ix < self.nx) & (iz >= 0) & (iz < self.nz)
        out = np.zeros(np.shape(x), dtype=bool)
        out[ok] = self.mask[ix[ok], iz[ok]]
        return out

    def wall_distances(self, positions: np.ndarray) -> np.ndarray:
        """``[n_positions, n_azimuths]`` horizontal distance to the first wall cell along each
        azimuth (clockwise from +z)."""
        az = np.radians(np.arange(0, 360, AZIMUTH_STEP))
        steps = np.arange(1, int(MAX_RANGE / CELL)) * CELL
        dx, dz = np.sin(az)[:, None] * steps, np.cos(az)[:, None] * steps
        out = np.empty((len(positions), len(az)))
        for i, (x, z) in enumerate(positions):
            inside = self.inside(x + dx, z + dz)
            first_out = np.argmin(inside, axis=1)  # index of first False
            first_out[inside.all(axis=1)] = len(steps) - 1
            out[i] = steps[first_out]
        return out


def wall_distance_lookup(table_row: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance along unit rays ``dirs`` to the wall, from one position's azimuth table."""
    horizontal = np.hypot(dirs[:, 0], dirs[:, 2])
    azimuth = np.degrees(np.arctan2(dirs[:, 0], dirs[:, 2])) % 360
    index = np.round(azimuth / AZIMUTH_STEP).astype(int) % len(table_row)
    with np.errstate(divide="ignore"):
        return np.where(horizontal > 1e-9, table_row[index] / horizontal, np.inf)


def obstacle_polygons(scene: Scene, margin: float) -> list[np.ndarray]:
    """Footprints (``[4, 2]`` xz corners) of objects that block motion: non-pickupable objects
    resting on the floor, each corner moved ``margin * sqrt(2)`` toward the centre. That moves each
    side of a square in by ``margin``, the long sides of an elongated footprint by less; an exact
    inward offset of every side would change 4 MoveAhead transitions of the 120 floor plans
    (docs/guide/simulator.md), and cached scenes and reported numbers depend on these."""
    polygons = []
    for obj in scene.objects:
        if obj.pickupable or obj.type in NON_OBSTACLE_TYPES or obj.box_min[1] > 0.15:
            continue
        if obj.footprint is not None:
            corners = np.asarray(obj.footprint, dtype=float)
        else:
            (x1, _, z1), (x2, _, z2) = obj.box_min, obj.box_max
            corners = np.array([[x1, z1], [x2, z1], [x2, z2], [x1, z2]])
        centre = corners.mean(axis=0)
        offsets = corners - centre
        lengths = np.linalg.norm(offsets, axis=1, keepdims=True)
        shrunk = centre + offsets * np.clip((lengths - margin * np.sqrt(2)) / np.maximum(lengths, 1e-9), 0, 1)
        polygons.append(shrunk)
    return polygons


def segment_hits_polygon(a: np.ndarray, b: np.ndarray, polygon: np.ndarray, samples: int = 9) -> bool:
    """True if any of ``samples`` points on segment a-b lies inside the convex ``polygon``."""
    t = np.linspace(0.0, 1.0, samples)[:, None]
    points = a + t * (b - a)
    edges = np.roll(polygon, -1, axis=0) - polygon
    rel = points[:, None, :] - polygon[None, :, :]
    cross = edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0]
    inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)
    return bool(inside.any())
