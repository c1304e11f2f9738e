"""Pictures for people: egocentric semantic views and top-down maps (matplotlib), and the
environment's top-down frames (numpy arrays)."""

from __future__ import annotations

import zlib
from dataclasses import replace

import numpy as np

from mapless.scenes.floor_plans import Scene
from mapless.sim.config import SimConfig
from mapless.sim.raycast import FLOOR, WALL, RayCaster
from mapless.sim.room import InteriorMask, obstacle_polygons
from mapless.sim.scene_data import SceneData

FLOOR_RGB = np.array([150, 140, 120])
WALL_RGB = np.array([200, 200, 210])


def type_colour(object_type: str) -> np.ndarray:
    """A stable, saturated RGB colour per object type."""
    h = zlib.crc32(object_type.encode()) % 360 / 360.0
    import colorsys

    return np.array(colorsys.hsv_to_rgb(h, 0.75, 0.95)) * 255


def egocentric_view(
    scene: Scene, config: SimConfig, x: float, z: float, yaw: int, horizon: int, size: int = 126
) -> np.ndarray:
    """``[size, size, 3]`` uint8 image: semantic colour per surface, shaded by depth."""
    size = size - size % 7
    caster = RayCaster(scene, replace(config, ray_resolution=size))
    walls = InteriorMask(scene, config.wall_clearance).wall_distances(np.array([[x, z]]))[0]
    frame = caster.render(x, z, yaw, horizon, walls)
    colours = np.array([type_colour(o.type) for o in scene.objects] + [FLOOR_RGB, WALL_RGB, [0, 0, 0]])
    n = len(scene.objects)  # colours: objects, then floor, wall and nothing (a ray that hit no surface)
    index = np.select([frame.ids >= 0, frame.ids == FLOOR, frame.ids == WALL], [frame.ids, n, n + 1], n + 2)
    shade = 1.0 / (1.0 + 0.25 * np.minimum(frame.depth, 20.0))
    image = colours[index] * (0.35 + 0.65 * shade)[:, None]
    return image.reshape(size, size, 3).clip(0, 255).astype(np.uint8)


def draw_top_down(
    ax,
    scene: Scene,
    config: SimConfig,
    highlight_types: tuple[str, ...] = (),
    pose: tuple[float, float, int, int] | None = None,
) -> None:
    """Top-down map on a matplotlib axis: interior, object boxes, obstacles, reachable grid, and the
    camera frustum of ``pose`` (x, z, yaw, horizon)."""
    from matplotlib.patches import Polygon, Rectangle

    interior = InteriorMask(scene, config.wall_clearance)
    extent = (interior.x0, interior.x0 + interior.nx * 0.02, interior.z0, interior.z0 + interior.nz * 0.02)
    ax.imshow(interior.mask.T, origin="lower", extent=extent, cmap="Greys_r", alpha=0.25, vmin=0, vmax=1)
    for obj in scene.objects:
        (x1, _, z1), (x2, _, z2) = obj.box_min, obj.box_max
        strong = obj.type in highlight_types
        ax.add_patch(
            Rectangle(
                (x1, z1),
                x2 - x1,
                z2 - z1,
                fill=strong,
                alpha=0.6 if strong else 0.5,
                edgecolor=type_colour(obj.type) / 255,
                facecolor=type_colour(obj.type) / 255,
                linewidth=2 if strong else 0.6,
            )
        )
        if strong:
            ax.annotate(obj.type, (obj.center[0], obj.center[2]), fontsize=7, ha="center")
    for poly in obstacle_polygons(scene, config.obstacle_margin):
        ax.add_patch(Polygon(poly, closed=True, fill=False, hatch="//", edgecolor="0.3", linewidth=0.5))
    ax.scatter(scene.reachable[:, 0], scene.reachable[:, 1], s=4, c="tab:blue", zorder=3)
    if pose is not None:
        x, z, yaw, _ = pose
        half = np.radians(config.horizontal_fov / 2)
        reach = 1.5
        left, right = np.radians(yaw) - half, np.radians(yaw) + half
        tri = np.array(
            [
                [x, z],
                [x + reach * np.sin(left), z + reach * np.cos(left)],
                [x + reach * np.sin(right), z + reach * np.cos(right)],
            ]
        )
        ax.add_patch(Polygon(tri, closed=True, alpha=0.3, color="orange", zorder=4))
        ax.plot([x], [z], "o", color="red", zorder=5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_title(f"{scene.name} ({scene.room_type})")


#: Colours of the top-down frame (:class:`TopDownFrame`).
_BACKGROUND_RGB = np.array([35, 35, 40])
_GRID_RGB = np.array([90, 120, 170])
_GOAL_RGB = np.array([60, 200, 90])
_TRAIL_RGB = np.array([250, 250, 250])
_AGENT_RGB = np.array([230, 40, 40])
_VIEW_RGB = np.array([255, 170, 40])


class TopDownFrame:
    """A scene seen from above as a ``[size, size, 3]`` uint8 array (no matplotlib, so that it is
    cheap enough for every step of a recorded video): the room's floor and objects (built-in scenes;
    a scene from another source has no geometry here and shows its pose grid alone), the reachable
    positions, the positions from which a target instance is visible (green), the target instances
    themselves, the path so far and the agent with its view cone.

    The static picture is drawn once per scene; :meth:`draw` paints one step over a copy of it."""

    def __init__(self, data: SceneData, size: int = 256, config: SimConfig | None = None):
        self.data, self.size = data, size
        self.config = config or SimConfig()
        scene = self._scene(data)
        xs, zs = data.x.astype(float), data.z.astype(float)
        if scene is not None:
            cx, _, cz = scene.floor_center
            sx, _, sz = scene.floor_size
            xs = np.concatenate([xs, [cx - sx / 2, cx + sx / 2]])
            zs = np.concatenate([zs, [cz - sz / 2, cz + sz / 2]])
        low = np.array([xs.min(), zs.min()]) - 0.5
        span = max(xs.max() - xs.min(), zs.max() - zs.min()) + 1.0
        self.scale = size / span  # pixels per metre
        # Centre the room in the square along its shorter side.
        self.origin = low - (span - (np.array([xs.max(), zs.max()]) + 0.5 - low)) / 2
        centres = (np.arange(size) + 0.5) / self.scale
        # Columns run along +x, rows along -z (z points up in the picture).
        self.world_x, self.world_z = np.meshgrid(self.origin[0] + centres, self.origin[1] + centres[::-1])
        self.scene = scene
        self.base = self._static()

    @staticmethod
    def _scene(data: SceneData) -> Scene | None:
        if data.meta.get("backend") != "geometric":
            return None
        from mapless.scenes.layout import load_scene

        return load_scene(data.scene)

    def _pixel(self, x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, column) of world points, clipped to the frame."""
        col = np.floor((np.asarray(x) - self.origin[0]) * self.scale).astype(int)
        row = self.size - 1 - np.floor((np.asarray(z) - self.origin[1]) * self.scale).astype(int)
        return np.clip(row, 0, self.size - 1), np.clip(col, 0, self.size - 1)

    def _box(self, obj) -> tuple[np.ndarray, np.ndarray]:
        """The pixels of an object's box seen from above, and those of its outline."""
        (x1, _, z1), (x2, _, z2) = obj.box_min, obj.box_max
        inside = (self.world_x >= x1) & (self.world_x <= x2) & (self.world_z >= z1) & (self.world_z <= z2)
        edge = 1.5 / self.scale
        core = (
            (self.world_x >= x1 + edge) & (self.world_x <= x2 - edge)
            & (self.world_z >= z1 + edge) & (self.world_z <= z2 - edge)
        )  # fmt: skip
        return inside, inside & ~core

    def _dots(self, image: np.ndarray, poses: np.ndarray, colour: np.ndarray, half: int) -> None:
        """Squares of ``2 * half + 1`` pixels at the positions of ``poses``."""
        rows, cols = self._pixel(self.data.x[poses], self.data.z[poses])
        for dr in range(-half, half + 1):
            for dc in range(-half, half + 1):
                image[np.clip(rows + dr, 0, self.size - 1), np.clip(cols + dc, 0, self.size - 1)] = colour

    def _static(self) -> np.ndarray:
        image = np.empty((self.size, self.size, 3))
        image[:] = _BACKGROUND_RGB
        if self.scene is not None:
            interior = InteriorMask(self.scene, self.config.wall_clearance)
            image[interior.inside(self.world_x, self.world_z)] = FLOOR_RGB
            # Largest first, so that a counter or a rug does not hide what stands on it.
            for obj in sorted(self.scene.objects, key=lambda o: -np.prod(o.size[::2])):
                box, outline = self._box(obj)
                image[box] = 0.8 * image[box] + 0.2 * type_colour(obj.type)
                image[outline] = type_colour(obj.type)
        self._dots(image, np.arange(self.data.n_poses), _GRID_RGB, 0)
        return image

    def draw(self, pose: int, goal: np.ndarray = (), trail: tuple[int, ...] | list[int] = ()) -> np.ndarray:
        """The frame of the agent at ``pose`` looking for the instances ``goal`` (indices into the
        scene's instances) after visiting the poses ``trail``."""
        data, image = self.data, self.base.copy()
        goal = np.asarray(goal, dtype=np.int64)
        if len(goal):
            self._dots(image, np.flatnonzero(data.goal_mask_for_instances(goal)), _GOAL_RGB, 2)
            if self.scene is not None:
                wanted = {data.instance_ids[i] for i in goal.tolist()}
                for obj in self.scene.objects:
                    if obj.id in wanted:
                        box, outline = self._box(obj)
                        image[box] = _GOAL_RGB
                        image[outline] = _TRAIL_RGB
        if len(trail):
            self._dots(image, np.asarray(trail, dtype=np.int64), _TRAIL_RGB, 1)
        x, z, yaw = float(data.x[pose]), float(data.z[pose]), np.radians(float(data.yaw[pose]))
        dx, dz = self.world_x - x, self.world_z - z
        distance = np.hypot(dx, dz)
        # Yaw turns clockwise from +z, so the heading is (sin yaw, cos yaw) in (x, z).
        off_axis = np.abs((np.arctan2(dx, dz) - yaw + np.pi) % (2 * np.pi) - np.pi)
        cone = (distance < 1.0) & (off_axis < np.radians(self.config.horizontal_fov / 2))
        image[cone] = 0.6 * image[cone] + 0.4 * _VIEW_RGB
        radius = max(0.12, 2.5 / self.scale)
        image[distance < radius] = _AGENT_RGB
        reach = np.linspace(radius, radius + 0.25, 32)  # the heading, out of the disc
        rows, cols = self._pixel(x + reach * np.sin(yaw), z + reach * np.cos(yaw))
        image[rows, cols] = _TRAIL_RGB
        return image.astype(np.uint8)
