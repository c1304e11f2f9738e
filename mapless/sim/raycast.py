"""Ray casting of one camera pose against the scene's object boxes, the floor and the walls.

Each pose casts a ``R x R`` grid of rays (one per ``300/R`` pixels). Every ray stops at the nearest
surface; the result is an instance-id buffer and a depth buffer, from which the in-view instances,
their occlusion-aware 2-D boxes, distances and the semantic feature map are derived.

Boxes: oriented boxes for movable objects (footprint from their OOBB), axis-aligned otherwise.
Open receptacles (shelves, counters, tables, beds, sinks...) are hollow for their contents: in the
depth test an open receptacle counts at the depth where the ray *leaves* its box, so anything inside
its volume (a pillow sunk into a bed box, a vase on a shelving unit) is seen in front of it, while
anything behind it stays hidden. Closed containers (fridge, drawers, cabinets, ... in their default
closed state) are solid, so their contents are occluded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapless.scenes.floor_plans import Scene
from mapless.sim.camera import camera_basis, pixel_rays, project
from mapless.sim.config import SimConfig
from mapless.sim.room import wall_distance_lookup

FLOOR, WALL, NOTHING = -2, -3, -1
_UNIT_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
#: The 12 edges of a box as pairs of indices into ``_UNIT_CORNERS`` (corners differing in one axis).
_EDGES = np.array([(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1])
_NEAR = 0.02  # m, near clipping plane for screen rectangles


@dataclass(frozen=True)
class Boxes:
    """Oriented boxes (rotation about y only): centre, half extents in the box frame, and the box
    frame's x axis as (cos a, sin a) in world xz."""

    centre: np.ndarray  # [M, 3]
    half: np.ndarray  # [M, 3]
    axis: np.ndarray  # [M, 2]
    hollow: np.ndarray  # [M] bool, open receptacles

    @classmethod
    def from_scene(cls, scene: Scene) -> Boxes:
        centre, half, axis = [], [], []
        for obj in scene.objects:
            c, s = np.asarray(obj.center, dtype=float), np.asarray(obj.size, dtype=float) / 2
            if obj.footprint is not None:
                corners = np.asarray(obj.footprint, dtype=float)
                e1, e2 = corners[1] - corners[0], corners[3] - corners[0]
                length1, length2 = np.linalg.norm(e1), np.linalg.norm(e2)
                if length1 > 1e-6 and length2 > 1e-6:
                    mid = corners.mean(axis=0)
                    c = np.array([mid[0], c[1], mid[1]])
                    s = np.array([length1 / 2, s[1], length2 / 2])
                    axis.append(e1 / length1)
                    centre.append(c)
                    half.append(s)
                    continue
            axis.append(np.array([1.0, 0.0]))
            centre.append(c)
            half.append(s)
        hollow = [o.receptacle and not o.hides_contents for o in scene.objects]
        return cls(
            np.array(centre, dtype=float).reshape(-1, 3),
            np.maximum(np.array(half, dtype=float).reshape(-1, 3), 1e-3),
            np.array(axis, dtype=float).reshape(-1, 2),
            np.array(hollow, dtype=bool),
        )

    def corners(self) -> np.ndarray:
        """``[M, 8, 3]`` world corners."""
        local = _UNIT_CORNERS[None] * self.half[:, None, :]
        cos, sin = self.axis[:, 0:1], self.axis[:, 1:2]
        x = local[..., 0] * cos - local[..., 2] * sin
        z = local[..., 0] * sin + local[..., 2] * cos
        return self.centre[:, None, :] + np.stack([x, local[..., 1], z], axis=-1)


@dataclass
class Frame:
    """Per-ray results of one pose (row-major ``R x R``)."""

    ids: np.ndarray  # int32: instance index, or FLOOR / WALL / NOTHING
    depth: np.ndarray  # m along the ray
    points: np.ndarray  # [R*R, 3] hit points


class RayCaster:
    def __init__(self, scene: Scene, config: SimConfig):
        self.config = config
        self.boxes = Boxes.from_scene(scene)
        self._corners = self.boxes.corners()
        self._rays = {
            (yaw, hor): pixel_rays(yaw, hor, config.ray_resolution, config.horizontal_fov)
            for yaw in config.yaws
            for hor in config.horizons
        }

    def _candidate_rects(self, eye: np.ndarray, yaw: float, horizon: float) -> np.ndarray:
        """``[M, 4]`` inclusive ray-grid rectangles (c0, r0, c1, r1) that can contain each box;
        empty (c0 > c1) when the box is outside the frustum. Boxes crossing the camera plane are
        clipped at a near plane first, so a counter beside the agent does not cover the screen."""
        res, fov = self.config.ray_resolution, self.config.horizontal_fov
        forward = camera_basis(yaw, horizon)[0]
        corners = self._corners
        depth = (corners - eye) @ forward
        p0, p1 = corners[:, _EDGES[:, 0]], corners[:, _EDGES[:, 1]]
        d0, d1 = depth[:, _EDGES[:, 0]], depth[:, _EDGES[:, 1]]
        crosses = (d0 - _NEAR) * (d1 - _NEAR) < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(crosses, (_NEAR - d0) / (d1 - d0), 0.0)
        clipped = p0 + t[..., None] * (p1 - p0)
        points = np.concatenate([corners, clipped], axis=1)
        valid = np.concatenate([depth > _NEAR, crosses], axis=1)
        pixels, _ = project(points.reshape(-1, 3), eye, yaw, horizon, fov, res)
        pixels = pixels.reshape(len(corners), points.shape[1], 2)
        lo = np.where(valid[..., None], pixels, np.inf).min(axis=1)
        hi = np.where(valid[..., None], pixels, -np.inf).max(axis=1)
        rects = np.empty((len(corners), 4), dtype=int)
        rects[:, :2] = np.clip(np.floor(np.clip(lo, -1, res + 1)), 0, res)
        rects[:, 2:] = np.clip(np.floor(np.clip(hi, -1, res + 1)), -1, res - 1)
        rects[~valid.any(axis=1)] = (1, 1, 0, 0)
        return rects

    def render(self, x: float, z: float, yaw: int, horizon: int, wall_row: np.ndarray) -> Frame:
        res = self.config.ray_resolution
        eye = np.array([x, self.config.eye_height, z])
        dirs = self._rays[(yaw, horizon)]
        n_rays = res * res

        # Background: floor plane y = 0 and the walls.
        with np.errstate(divide="ignore"):
            t_floor = np.where(dirs[:, 1] < -1e-9, -eye[1] / dirs[:, 1], np.inf)
        t_wall = wall_distance_lookup(wall_row, dirs)
        ids = np.where(t_floor < t_wall, FLOOR, WALL).astype(np.int32)
        depth = np.minimum(t_floor, t_wall)
        key = depth.copy()

        # Enumerate (box, ray) pairs inside each box's screen rectangle.
        rects = self._candidate_rects(eye, yaw, horizon)
        widths = np.maximum(rects[:, 2] - rects[:, 0] + 1, 0)
        heights = np.maximum(rects[:, 3] - rects[:, 1] + 1, 0)
        counts = widths * heights
        boxes = np.flatnonzero(counts)
        if len(boxes):
            counts_b = counts[boxes]
            box_of_pair = np.repeat(boxes, counts_b)
            starts = np.repeat(np.cumsum(counts_b) - counts_b, counts_b)
            local = np.arange(counts_b.sum()) - starts
            w = widths[box_of_pair]
            cols = rects[box_of_pair, 0] + local % w
            rows = rects[box_of_pair, 1] + local // w
            ray = rows * res + cols
            t_in, t_out = self._slab(eye, dirs[ray], box_of_pair)
            hit = (t_out >= t_in) & (t_in > 1e-3)
            box_of_pair, ray, t_in, t_out = box_of_pair[hit], ray[hit], t_in[hit], t_out[hit]
            pair_key = np.where(self.boxes.hollow[box_of_pair], t_out, t_in)
            front = pair_key < key[ray]
            box_of_pair, ray, t_in, pair_key = box_of_pair[front], ray[front], t_in[front], pair_key[front]
            np.minimum.at(key, ray, pair_key)
            winner = pair_key == key[ray]
            ids[ray[winner]] = box_of_pair[winner]
            depth[ray[winner]] = t_in[winner]
        points = eye + dirs * np.minimum(depth, 1e3)[:, None]
        assert len(ids) == n_rays
        return Frame(ids=ids, depth=depth, points=points)

    def _slab(self, eye: np.ndarray, dirs: np.ndarray, box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Entry and exit distances of rays through their boxes (slab test in the box frame). The
        camera's position in every box frame is computed once per pose, then gathered per pair."""
        cos_all, sin_all = self.boxes.axis[:, 0], self.boxes.axis[:, 1]
        rel = eye - self.boxes.centre
        origin = np.stack(
            [
                rel[:, 0] * cos_all + rel[:, 2] * sin_all,
                rel[:, 1],
                -rel[:, 0] * sin_all + rel[:, 2] * cos_all,
            ],
            1,
        )
        low, high = -self.boxes.half - origin, self.boxes.half - origin
        cos, sin = cos_all[box], sin_all[box]
        local = (dirs[:, 0] * cos + dirs[:, 2] * sin, dirs[:, 1], -dirs[:, 0] * sin + dirs[:, 2] * cos)
        t_in = np.full(len(box), -np.inf)
        t_out = np.full(len(box), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for axis, d in enumerate(local):
                inv = 1.0 / d
                t1, t2 = low[box, axis] * inv, high[box, axis] * inv
                t1 = np.where(np.isnan(t1), -np.inf, t1)  # 0 * inf: the ray lies in the slab's plane
                t2 = np.where(np.isnan(t2), np.inf, t2)
                t_in = np.maximum(t_in, np.minimum(t1, t2))
                t_out = np.minimum(t_out, np.maximum(t1, t2))
        return t_in, t_out
