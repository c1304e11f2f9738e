"""Pinhole camera in Unity's frame: x right, y up, z forward; yaw clockwise from +z seen from above;
horizon positive when looking down."""

from __future__ import annotations

import numpy as np


def camera_basis(yaw_deg: float, horizon_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(forward, right, up) unit vectors of a camera with the given yaw and horizon."""
    yaw, pitch = np.radians(yaw_deg), np.radians(horizon_deg)
    forward = np.array([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
    right = np.array([np.cos(yaw), 0.0, -np.sin(yaw)])
    up = np.cross(forward, right)  # left-handed frame: forward x right points up
    return forward, right, up


def pixel_rays(yaw_deg: float, horizon_deg: float, resolution: int, fov_deg: float) -> np.ndarray:
    """Unit ray directions ``[resolution * resolution, 3]``, row-major from the top-left pixel."""
    forward, right, up = camera_basis(yaw_deg, horizon_deg)
    half = np.tan(np.radians(fov_deg) / 2)
    centres = (np.arange(resolution) + 0.5) / resolution * 2 - 1
    cols, rows = np.meshgrid(centres * half, -centres * half)
    dirs = forward + cols.reshape(-1, 1) * right + rows.reshape(-1, 1) * up
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def project(
    points: np.ndarray, eye: np.ndarray, yaw_deg: float, horizon_deg: float, fov_deg: float, size: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``[n, 2]`` (column, row; origin top-left) of world points in a ``size``
    square frame, and their depth along the optical axis (<= 0 means behind the camera)."""
    forward, right, up = camera_basis(yaw_deg, horizon_deg)
    rel = np.asarray(points, dtype=float) - eye
    depth = rel @ forward
    half = np.tan(np.radians(fov_deg) / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (rel @ right) / depth / half
        v = (rel @ up) / depth / half
    pixels = np.stack([(u + 1) / 2 * size, (1 - v) / 2 * size], axis=-1)
    return pixels, depth
