"""Pictures for people: egocentric semantic views and top-down maps (matplotlib)."""

from __future__ import annotations

import zlib
from dataclasses import replace

import numpy as np

from mapless.scenes.floor_plans import Scene
from mapless.sim.config import SimConfig
from mapless.sim.raycast import FLOOR, WALL, RayCaster
from mapless.sim.room import InteriorMask, obstacle_polygons

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
