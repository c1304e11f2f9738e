"""Live AI2-THOR backend (optional extra ``mapless[thor]``).

It drives an ``ai2thor.controller.Controller`` configured like the SAVN/MJOLNIR data (0.25 m grid,
45 degree rotations, the configured horizons, a visibility distance, 300x300 frames, instance
segmentation on) and turns events into what the rest of mapless consumes:

* :func:`observation_from_event`: the per-step observation (``context`` ``[C, 4]`` from the
  ``instance_detections2D`` boxes, semantic ``features`` ``[F, 7, 7]`` from the instance masks and
  the depth frame, the ids whose metadata ``visible`` flag is set) - the same quantities the
  geometric simulator precomputes per pose;
* :class:`LiveThorScene`: step a scene live with the offline transition rule (moves are teleports
  to the geometrically guessed pose, as SAVN's ``ExhaustiveBFSController`` generated its graphs);
* :func:`scrape_scene` / :func:`scrape`: breadth-first search over poses into a :class:`SceneData`
  and an offline folder in the SAVN/MJOLNIR format.

``ai2thor`` is imported only by :func:`make_controller`; everything else works on any object with
the documented ``Controller``/``Event`` surface (``step(action=..., **kwargs)``, ``reset(scene)``,
``event.metadata``, ``event.instance_detections2D``, ``event.instance_masks``,
``event.depth_frame``, ``event.frame``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mapless.actions import DONE, N_MOVEMENT_ACTIONS
from mapless.errors import MaplessError
from mapless.offline.format import (
    FEATURE_SIDE,
    IMAGES_FILE,
    category_rows,
    context_from_boxes,
    guess_next_keys,
    parse_pose_key,
    scene_folder_name,
)
from mapless.sim.config import SimConfig
from mapless.sim.scene_data import SceneData, pose_key

MAX_FEATURE_DEPTH = 10.0  # m, as in the geometric simulator's depth channel
FEATURE_SCALE = 1.0 / 255.0
FeatureExtractor = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class ThorConfig:
    """Controller settings: the geometric simulator's ``sim`` settings (grid, rotation step,
    horizons, visibility distance, square ``image_size`` frames, field of view, category set; the
    defaults follow the SAVN/MJOLNIR data) plus what only a live AI2-THOR needs. The rest of
    ``sim`` (eye height, ray resolution, obstacle margins...) concerns the geometric simulator only.
    """

    sim: SimConfig = field(default_factory=SimConfig)
    render_depth: bool = True
    #: ``"CloudRendering"`` for headless Vulkan rendering; None = ai2thor's default (needs X).
    platform: str | None = None
    #: Further ``Controller`` keyword arguments (``commit_id``, ``local_executable_path``...).
    extra: dict = field(default_factory=dict)

    def controller_kwargs(self) -> dict[str, Any]:
        kwargs: dict[str, Any] = {
            "agentMode": "default",
            "gridSize": self.sim.grid_size,
            "rotateStepDegrees": self.sim.rotation_step,
            "visibilityDistance": self.sim.visibility_distance,
            "width": self.sim.image_size,
            "height": self.sim.image_size,
            "fieldOfView": self.sim.horizontal_fov,
            "renderInstanceSegmentation": True,
            "renderDepthImage": self.render_depth,
        }
        kwargs.update(self.extra)
        return kwargs


def make_controller(scene: str, config: ThorConfig | None = None) -> Any:
    """A real ``ai2thor.controller.Controller`` (the first run downloads the Unity build)."""
    config = config or ThorConfig()
    try:
        from ai2thor.controller import Controller
    except ImportError:
        raise MaplessError(
            "AI2-THOR is not installed; install the optional extra with "
            "`pip install -c constraints.txt 'mapless[thor]'`"
        ) from None
    kwargs = config.controller_kwargs()
    if config.platform:
        import ai2thor.platform

        kwargs["platform"] = getattr(ai2thor.platform, config.platform)
    return Controller(scene=scene, **kwargs)


# ------------------------------------------------------------------------------- event decoding


@dataclass(frozen=True)
class ObjectTable:
    """The scene's instances (from the metadata ``objects`` list) and their category rows."""

    ids: tuple[str, ...]
    types: tuple[str, ...]
    index: dict[str, int]
    rows: np.ndarray
    n_categories: int

    @classmethod
    def from_event(cls, event: Any, category_set_name: str) -> ObjectTable:
        from mapless.scenes.categories import category_set

        objects = event.metadata.get("objects") or []
        ids = tuple(o["objectId"] for o in objects)
        types = tuple(o["objectType"] for o in objects)
        return cls(
            ids,
            types,
            {k: i for i, k in enumerate(ids)},
            category_rows(types, category_set_name),
            len(category_set(category_set_name)),
        )


def view_entries(event: Any, table: ObjectTable) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """In-view instances of an event (sorted), their boxes, distances and visible flags.

    In view = has an ``instance_detections2D`` box (occlusion-aware, any distance) or is flagged
    ``visible``. THOR boxes are inclusive pixel indices; the +1 on x2/y2 makes them pixel extents
    like the simulator's. Visible = the metadata ``visible`` flag (in frame, within
    ``visibilityDistance``), the success rule of the offline data.
    """
    detections = getattr(event, "instance_detections2D", None) or {}
    rows = []
    for obj in event.metadata.get("objects") or []:
        i = table.index.get(obj["objectId"])
        if i is None:
            continue
        box = detections.get(obj["objectId"])
        if box is None and not obj.get("visible"):
            continue
        if box is None:
            box4 = (0.0, 0.0, 0.0, 0.0)
        else:
            x1, y1, x2, y2 = (float(v) for v in box)
            box4 = (x1, y1, x2 + 1, y2 + 1)
        rows.append((i, box4, float(obj.get("distance", np.nan)), bool(obj.get("visible"))))
    rows.sort(key=lambda r: r[0])
    return (
        np.array([r[0] for r in rows], dtype=np.int32),
        np.array([r[1] for r in rows], dtype=np.float32).reshape(-1, 4),
        np.array([r[2] for r in rows], dtype=np.float32),
        np.array([r[3] for r in rows], dtype=bool),
    )


def _structure_channel(object_id: str, n_categories: int) -> int:
    head = object_id.split("|", 1)[0].lower()
    if "floor" in head:
        return n_categories
    if "wall" in head:
        return n_categories + 1
    return -1


def semantic_features(event: Any, table: ObjectTable) -> np.ndarray:
    """``[C + 3, 7, 7]`` uint8 (scale 1/255): per 7x7 cell the pixel fraction of each category
    (instance masks), of floor and of walls, and the mean depth / 10 m (0 without a depth frame).
    The same channels as the geometric simulator's feature map."""
    n_cat = table.n_categories
    out = np.zeros((n_cat + 3, FEATURE_SIDE, FEATURE_SIDE), dtype=np.uint8)
    masks = getattr(event, "instance_masks", None) or {}
    depth = getattr(event, "depth_frame", None)
    coverage = np.zeros((n_cat + 2, FEATURE_SIDE, FEATURE_SIDE))
    for object_id, mask in masks.items():
        i = table.index.get(object_id)
        channel = int(table.rows[i]) if i is not None else _structure_channel(object_id, n_cat)
        if channel < 0:
            continue
        coverage[channel] += _cell_means(np.asarray(mask, dtype=np.float64))
    out[: n_cat + 2] = np.round(np.clip(coverage, 0, 1) * 255)
    if depth is not None:
        depth = np.asarray(depth, dtype=np.float64)
        out[n_cat + 2] = np.round(_cell_means(np.minimum(depth, MAX_FEATURE_DEPTH)) / MAX_FEATURE_DEPTH * 255)
    return out


def _cell_means(image: np.ndarray) -> np.ndarray:
    """Mean of an ``H x W`` image over a 7x7 grid of (nearly) equal cells."""
    h, w = image.shape
    rows = np.minimum(np.arange(h) * FEATURE_SIDE // h, FEATURE_SIDE - 1)
    cols = np.minimum(np.arange(w) * FEATURE_SIDE // w, FEATURE_SIDE - 1)
    sums = np.zeros((FEATURE_SIDE, FEATURE_SIDE))
    np.add.at(sums, (rows[:, None], cols[None, :]), image)
    counts = (
        np.bincount(rows, minlength=FEATURE_SIDE)[:, None]
        * np.bincount(cols, minlength=FEATURE_SIDE)[None, :]
    )
    return sums / counts


def observation_from_event(event: Any, table: ObjectTable, image_size: int = 300) -> dict[str, Any]:
    """The observation quantities of one live step: ``context`` float32 ``[C, 4]``, ``features``
    float32 ``[C + 3, 7, 7]``, ``visible_ids`` (success rule) and ``in_view_ids``."""
    inst, boxes, _, visible = view_entries(event, table)
    context = context_from_boxes(table.rows[inst], boxes, table.n_categories, image_size)
    return {
        "context": context,
        "features": semantic_features(event, table).astype(np.float32) * np.float32(FEATURE_SCALE),
        "visible_ids": tuple(table.ids[i] for i in inst[visible]),
        "in_view_ids": tuple(table.ids[i] for i in inst),
    }


def _agent_key(event: Any) -> str:
    agent = event.metadata["agent"]
    horizon = round(agent["cameraHorizon"])
    horizon = horizon - 360 if horizon > 180 else horizon  # some THOR versions say 330 for -30
    return pose_key(
        round(agent["position"]["x"], 2),
        round(agent["position"]["z"], 2),
        round(agent["rotation"]["y"]) % 360,
        horizon,
    )


def teleport(controller: Any, key: str, y: float) -> Any | None:
    """Teleport to a pose key; the event, or None if THOR refused or put the agent elsewhere."""
    x, z, yaw, horizon = parse_pose_key(key)
    event = controller.step(
        action="Teleport",
        position={"x": x, "y": y, "z": z},
        rotation={"x": 0, "y": yaw, "z": 0},
        horizon=horizon,
        standing=True,
    )
    if not event.metadata.get("lastActionSuccess"):
        return None
    return event if parse_pose_key(_agent_key(event)) == parse_pose_key(key) else None


# --------------------------------------------------------------------------------- live stepping


class LiveThorScene:
    """A scene stepped live in AI2-THOR with the offline transition rule.

    Moves are teleports to the geometric guess of the action (diagonal MoveAhead by (+-g, +-g),
    45 degree turns, horizon steps of 30 limited to ``config.sim.horizons``), so a live episode follows
    exactly the transitions of a scraped offline folder.
    """

    def __init__(self, controller: Any, config: ThorConfig | None = None):
        self.controller = controller
        self.config = config or ThorConfig()
        self.table: ObjectTable | None = None
        self.event: Any = None
        self.agent_y = 0.0

    def reset(self, scene: str, start: str | None = None) -> dict[str, Any]:
        """Load ``scene`` and teleport to ``start`` (a pose key), or stay at the spawn pose."""
        self.event = self.controller.reset(scene=scene)
        self.table = ObjectTable.from_event(self.event, self.config.sim.category_set)
        self.agent_y = float(self.event.metadata["agent"]["position"]["y"])
        if start is not None:
            event = teleport(self.controller, start, self.agent_y)
            if event is None:
                raise MaplessError(f"start pose {start} is not reachable in {scene}")
            self.event = event
        return self.observation()

    @property
    def pose(self) -> str:
        return _agent_key(self.event)

    def step(self, action: int) -> tuple[dict[str, Any], bool]:
        """Apply a movement action (``Done`` is the environment's business: no-op here)."""
        if self.event is None:
            raise MaplessError("LiveThorScene.step before reset")
        moved = False
        if action != DONE:
            if not 0 <= action < N_MOVEMENT_ACTIONS:
                raise MaplessError(f"unknown action {action}; valid: 0-5")
            guess = _allowed_guess(self.pose, action, self.config.sim)
            event = teleport(self.controller, guess, self.agent_y) if guess else None
            if event is not None:
                self.event, moved = event, True
            else:  # THOR may have moved before refusing: go back to the pose we had
                event = teleport(self.controller, self.pose, self.agent_y)
                self.event = event if event is not None else self.event
        return self.observation(), moved

    def observation(self) -> dict[str, Any]:
        obs = observation_from_event(self.event, self.table, self.config.sim.image_size)
        obs["pose"] = self.pose
        return obs


def _allowed_guess(key: str, action: int, sim: SimConfig) -> str | None:
    for guess in guess_next_keys(key, action, sim.grid_size, sim.rotation_step):
        _, _, yaw, horizon = parse_pose_key(guess)
        if horizon in sim.horizons and yaw % sim.rotation_step == 0:
            return guess
    return None


# -------------------------------------------------------------------------------------- scraping


def scrape_scene(
    controller: Any,
    scene: str,
    config: ThorConfig | None = None,
    *,
    feature_extractor: FeatureExtractor | None = None,
    on_frame: Callable[[str, np.ndarray], None] | None = None,
    progress: bool = False,
) -> SceneData:
    """Breadth-first search over the poses of ``scene`` into a :class:`SceneData`.

    Seeds: every position of ``GetReachablePositions`` at yaw 0 and the first horizon. For each
    dequeued pose the 5 movement actions are tried by teleporting to their geometric guess (as
    SAVN's ``ExhaustiveBFSController`` did); a pose THOR accepts becomes a node, and the action an
    edge. Each new pose is recorded: in-view instances, boxes, distances, ``visible`` flags,
    context, features (semantic from masks and depth, or ``feature_extractor(frame)`` e.g. a
    ResNet-18 returning ``[512, 7, 7]``); ``on_frame(key, frame)`` sees every RGB frame.
    """
    config = config or ThorConfig()
    sim = config.sim
    event = controller.reset(scene=scene)
    table = ObjectTable.from_event(event, sim.category_set)
    reachable = controller.step(action="GetReachablePositions").metadata.get("actionReturn") or []
    if not reachable:
        raise MaplessError(f"AI2-THOR returned no reachable positions for {scene}")
    agent_y = float(reachable[0].get("y", event.metadata["agent"]["position"]["y"]))
    start_horizon = 0 if 0 in sim.horizons else sim.horizons[0]

    keys: list[str] = []
    index: dict[str, int] = {}
    refused: set[str] = set()
    edges: list[tuple[int, int, int]] = []
    records: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    features: list[np.ndarray] = []

    def visit(key: str) -> int | None:
        if key in index:
            return index[key]
        if key in refused:
            return None
        ev = teleport(controller, key, agent_y)
        if ev is None:
            refused.add(key)
            return None
        index[key] = len(keys)
        keys.append(key)
        records.append(view_entries(ev, table))
        frame = getattr(ev, "frame", None)
        if feature_extractor is not None:
            if frame is None:
                raise MaplessError("a feature extractor needs RGB frames, but the event has none")
            features.append(np.asarray(feature_extractor(frame), dtype=np.float32).reshape(-1, 7, 7))
        else:
            features.append(semantic_features(ev, table))
        if on_frame is not None and frame is not None:
            on_frame(key, np.asarray(frame))
        queue.append(key)
        return index[key]

    queue: deque[str] = deque()
    seeds = dict.fromkeys(pose_key(round(p["x"], 2), round(p["z"], 2), 0, start_horizon) for p in reachable)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(desc=scene, unit="pose", leave=False)
    for seed in seeds:
        visit(seed)
        while queue:
            key = queue.popleft()
            if bar is not None:
                bar.update()
            for action in range(N_MOVEMENT_ACTIONS):
                guess = _allowed_guess(key, action, sim)
                target = visit(guess) if guess else None
                if target is not None:
                    edges.append((index[key], action, target))
    if bar is not None:
        bar.close()

    n = len(keys)
    successors = np.repeat(np.arange(n, dtype=np.int32)[:, None], N_MOVEMENT_ACTIONS, axis=1)
    for s, action, t in edges:
        successors[s, action] = t
    poses = np.array([parse_pose_key(k) for k in keys], dtype=np.float64).reshape(-1, 4)
    view_ptr = np.concatenate([[0], np.cumsum([len(r[0]) for r in records])]).astype(np.int64)
    context = np.stack(
        [context_from_boxes(table.rows[r[0]], r[1], table.n_categories, sim.image_size) for r in records]
    )

    def flat(j: int, dtype: Any, width: int | None = None) -> np.ndarray:
        parts = [r[j] for r in records]
        joined = np.concatenate(parts) if parts else np.zeros(0)
        return joined.astype(dtype).reshape(-1, width) if width else joined.astype(dtype)

    from mapless.scenes.catalogue import room_type_of

    try:
        room = room_type_of(scene)
    except MaplessError:
        room = "unknown"
    return SceneData.from_poses(
        poses,
        scene=scene,
        room_type=room,
        successors=successors,
        instance_ids=table.ids,
        instance_types=table.types,
        view_ptr=view_ptr,
        view_instance=flat(0, np.int32),
        view_box=flat(1, np.float32, 4),
        view_distance=flat(2, np.float32),
        view_visible=flat(3, bool),
        context=context.astype(np.float32),
        features=np.stack(features),
        feature_scale=1.0 if feature_extractor is not None else FEATURE_SCALE,
        meta={
            "backend": "thor",
            "category_set": sim.category_set,
            "feature_kind": "resnet18" if feature_extractor is not None else "semantic",
            "agent_y": agent_y,
            "visibility_distance": sim.visibility_distance,
        },
    )


def scrape(
    controller: Any,
    scene: str,
    out_dir: str | Path,
    format: str = "savn",
    config: ThorConfig | None = None,
    *,
    images: bool = False,
    feature_extractor: FeatureExtractor | None = None,
    progress: bool = False,
) -> Path:
    """Scrape ``scene`` with a live controller into ``out_dir/<scene folder>/`` in the offline
    format (plus ``images.hdf5`` with the RGB frames when ``images``); returns the folder."""
    from mapless.offline.writer import export_scene

    folder = Path(out_dir) / scene_folder_name(scene, format)
    on_frame = None
    handle = None
    if images:
        import h5py

        folder.mkdir(parents=True, exist_ok=True)
        handle = h5py.File(folder / IMAGES_FILE, "w")

        def on_frame(key: str, frame: np.ndarray) -> None:
            handle.create_dataset(key, data=frame.astype(np.uint8), compression="gzip")

    try:
        sd = scrape_scene(
            controller,
            scene,
            config,
            feature_extractor=feature_extractor,
            on_frame=on_frame,
            progress=progress,
        )
    finally:
        if handle is not None:
            handle.close()
    return export_scene(sd, out_dir, format)
