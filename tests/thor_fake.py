"""A stand-in for ``ai2thor.controller.Controller`` reproducing the documented Event surface.

The world: a 3x3 grid of reachable positions (one cell missing), four objects, a pinhole camera
with a 90 degree field of view. ``visible`` = in frame and within ``visibilityDistance`` of the
eye; ``instance_detections2D`` holds inclusive pixel boxes of everything in frame (plus a floor
and a wall), ``instance_masks`` the same rectangles, ``depth_frame`` a constant plane.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

EYE_HEIGHT = 1.5
OBJECTS = (
    ("Mug|+00.50|+00.90|+00.75", "Mug", (0.5, 0.9, 0.75)),
    ("Toaster|-00.75|+00.90|+00.25", "Toaster", (-0.75, 0.9, 0.25)),
    ("DiningTable|+00.00|+00.00|+01.25", "DiningTable", (0.0, 0.4, 1.25)),
    ("Fridge|+00.00|+00.00|-00.75", "Fridge", (0.0, 0.9, -0.75)),
)
REACHABLE = tuple((x, z) for x in (-0.25, 0.0, 0.25) for z in (0.0, 0.25, 0.5) if (x, z) != (0.25, 0.5))


class FakeEvent:
    def __init__(self, metadata: dict, detections: dict, masks: dict, depth: np.ndarray, frame: np.ndarray):
        self.metadata = metadata
        self.instance_detections2D = detections
        self.instance_masks = masks
        self.depth_frame = depth
        self.frame = frame


class FakeController:
    def __init__(
        self,
        scene: str = "FloorPlan5",
        visibilityDistance: float = 1.0,
        width: int = 300,
        height: int = 300,
        **kwargs: Any,
    ):
        self.visibility_distance = visibilityDistance
        self.size = width
        self.kwargs = kwargs
        self.scene = scene
        self.teleports = 0
        self.reset(scene)

    # -- the Controller surface used by mapless.thor
    def reset(self, scene: str | None = None, **kwargs: Any) -> FakeEvent:
        self.scene = scene or self.scene
        self.state = (REACHABLE[0][0], REACHABLE[0][1], 0, 0)
        self.last_event = self.render(True)
        return self.last_event

    def step(self, action: str | None = None, **kwargs: Any) -> FakeEvent:
        if action == "GetReachablePositions":
            event = self.render(True)
            event.metadata["actionReturn"] = [{"x": x, "y": 0.9, "z": z} for x, z in REACHABLE]
        elif action == "Teleport":
            self.teleports += 1
            x, z = kwargs["position"]["x"], kwargs["position"]["z"]
            yaw, horizon = kwargs["rotation"]["y"], kwargs["horizon"]
            ok = (round(x, 2), round(z, 2)) in REACHABLE and -30 <= horizon <= 60
            if ok:
                self.state = (x, z, int(yaw) % 360, int(horizon))
            event = self.render(ok)
        else:
            event = self.render(False)
            event.metadata["errorMessage"] = f"fake controller: unsupported action {action}"
        self.last_event = event
        return event

    def stop(self) -> None:
        pass

    # -- the fake world
    def project(
        self, pose: tuple[float, float, int, int]
    ) -> dict[str, tuple[tuple[int, int, int, int], float]]:
        """Objects in frame at a pose: id -> (inclusive pixel box, distance)."""
        x, z, yaw, horizon = pose
        out = {}
        half = self.size / 2
        for object_id, _, (ox, oy, oz) in OBJECTS:
            dx, dz, dy = ox - x, oz - z, oy - EYE_HEIGHT
            ground = math.hypot(dx, dz)
            bearing = math.degrees(math.atan2(dx, dz)) - yaw
            bearing = (bearing + 180) % 360 - 180
            elevation = math.degrees(math.atan2(dy, ground)) + horizon
            if abs(bearing) >= 44 or abs(elevation) >= 44:
                continue
            u = half + half * math.tan(math.radians(bearing))
            v = half - half * math.tan(math.radians(elevation))
            r = max(2, int(20 / max(ground, 0.1)))
            box = (
                max(0, int(u) - r),
                max(0, int(v) - r),
                min(self.size - 1, int(u) + r),
                min(self.size - 1, int(v) + r),
            )
            out[object_id] = (box, math.sqrt(ground**2 + dy**2))
        return out

    def visible_ids(self, pose: tuple[float, float, int, int]) -> set[str]:
        return {k for k, (_, d) in self.project(pose).items() if d <= self.visibility_distance}

    def render(self, success: bool) -> FakeEvent:
        x, z, yaw, horizon = self.state
        seen = self.project(self.state)
        objects = [
            {
                "objectId": object_id,
                "objectType": object_type,
                "position": {"x": ox, "y": oy, "z": oz},
                "visible": object_id in seen and seen[object_id][1] <= self.visibility_distance,
                "distance": seen[object_id][1] if object_id in seen else math.hypot(ox - x, oz - z),
            }
            for object_id, object_type, (ox, oy, oz) in OBJECTS
        ]
        detections = {k: box for k, (box, _) in seen.items()}
        detections["Floor|+00.00|+00.00|+00.00"] = (0, 200, self.size - 1, self.size - 1)
        detections["Wall|1"] = (0, 0, self.size - 1, 50)
        masks = {}
        for key, (x1, y1, x2, y2) in detections.items():
            mask = np.zeros((self.size, self.size), dtype=bool)
            mask[y1 : y2 + 1, x1 : x2 + 1] = True
            masks[key] = mask
        metadata = {
            "lastActionSuccess": success,
            "errorMessage": "" if success else "fake controller: pose not reachable",
            "sceneName": self.scene,
            "agent": {
                "position": {"x": x, "y": 0.9, "z": z},
                "rotation": {"x": 0, "y": float(yaw), "z": 0},
                "cameraHorizon": float(horizon),
            },
            "objects": objects,
            "actionReturn": None,
        }
        depth = np.full((self.size, self.size), 2.0 + horizon / 100, dtype=np.float32)
        frame = np.full((self.size, self.size, 3), yaw % 256, dtype=np.uint8)
        return FakeEvent(metadata, detections, masks, depth, frame)
