"""``SceneData``: everything an episode step needs, precomputed per scene and indexed by pose id.

It is the one interface between scene backends (the built-in geometric simulator, a SAVN/MJOLNIR
offline folder, a live AI2-THOR scrape) and everything downstream (environments, evaluation,
export). An episode step is array indexing into it.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from mapless.errors import MaplessError

#: A pose-graph component smaller than this share of the scene's largest is an island (SceneData.usable_poses).
USABLE_COMPONENT_SHARE = 0.25


def pose_key(x: float, z: float, yaw: int, horizon: int) -> str:
    """SAVN/MJOLNIR pose key ``"x|z|rotation|horizon"`` (two decimals; ``-0.00`` kept as Python prints it)."""
    return f"{x:.2f}|{z:.2f}|{int(yaw)}|{int(horizon)}"


@dataclass
class SceneData:
    """Per-pose arrays of one scene.

    Poses: ``x``, ``z`` (m), ``yaw`` (deg, clockwise from +z), ``horizon`` (deg, positive = down).
    ``successors[p, a]`` is the pose after movement action ``a`` (0-4) or ``p`` itself when the
    action fails. In-view instances are stored in CSR form: the entries of pose ``p`` are
    ``view_ptr[p]:view_ptr[p+1]`` of ``view_instance`` (index into ``instance_ids``), ``view_box``
    (occlusion-aware 2-D box ``x1, y1, x2, y2`` in pixels of the 300x300 frame), ``view_distance``
    (m, the rule's distance) and ``view_visible`` (the success rule: in view, not in a closed
    receptacle, within the visibility distance).
    ``context[p]`` is ``[C, 4]`` (docs/guide/simulator.md, "Observations"); ``features[p]`` is ``[F, 7, 7]`` stored as
    ``features_dtype`` and multiplied by ``feature_scale`` when read.
    """

    scene: str
    room_type: str
    x: np.ndarray
    z: np.ndarray
    yaw: np.ndarray
    horizon: np.ndarray
    successors: np.ndarray
    instance_ids: tuple[str, ...]
    instance_types: tuple[str, ...]
    view_ptr: np.ndarray
    view_instance: np.ndarray
    view_box: np.ndarray
    view_distance: np.ndarray
    view_visible: np.ndarray
    context: np.ndarray
    features: np.ndarray
    feature_scale: float = 1.0 / 255.0
    meta: dict = field(default_factory=dict)
    _distance_cache: dict = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_poses(cls, poses: np.ndarray, **fields) -> SceneData:
        """Build from a ``[P, 4]`` array of ``(x, z, yaw, horizon)`` rows plus the other fields."""
        return cls(
            x=poses[:, 0].astype(np.float32),
            z=poses[:, 1].astype(np.float32),
            yaw=poses[:, 2].astype(np.int16),
            horizon=poses[:, 3].astype(np.int16),
            **fields,
        )

    @property
    def n_poses(self) -> int:
        return len(self.x)

    @functools.cached_property
    def pose_index(self) -> dict[str, int]:
        return {self.key(p): p for p in range(self.n_poses)}

    def key(self, pose: int) -> str:
        return pose_key(self.x[pose], self.z[pose], self.yaw[pose], self.horizon[pose])

    def pose_tuple(self, pose: int) -> tuple[float, float, int, int]:
        """``(x, z, yaw, horizon)`` of a pose id, as plain Python numbers (an episode's ``start``)."""
        return float(self.x[pose]), float(self.z[pose]), int(self.yaw[pose]), int(self.horizon[pose])

    def in_view(self, pose: int) -> np.ndarray:
        return self.view_instance[self.view_ptr[pose] : self.view_ptr[pose + 1]]

    def visible(self, pose: int) -> np.ndarray:
        s = slice(self.view_ptr[pose], self.view_ptr[pose + 1])
        return self.view_instance[s][self.view_visible[s]]

    def instances_of(self, object_type: str) -> np.ndarray:
        return np.flatnonzero(np.asarray(self.instance_types) == object_type)

    def goal_instances(self, object_type: str, instance_ids: Sequence[str] = ()) -> np.ndarray:
        """Indices of an episode's goal instances: those of ``instance_ids`` (an episode that names
        its instances, as SAVN's do), else every instance of ``object_type``. An id this scene lacks
        is an error: silently dropped, it would make the episode unwinnable (episodes made for
        another version of the scene's data, e.g. v5 ids on a v1 offline root)."""
        if not instance_ids:
            return self.instances_of(object_type)
        index = {iid: i for i, iid in enumerate(self.instance_ids)}
        missing = [i for i in instance_ids if i not in index]
        if missing:
            raise MaplessError(
                f"{self.scene} has no object {', '.join(missing)} (an episode's target instances); "
                "were its episodes made for another version of this scene's data?"
            )
        return np.array([index[i] for i in instance_ids], dtype=np.int64)

    @functools.cached_property
    def view_pose(self) -> np.ndarray:
        """The pose of each in-view entry, aligned with ``view_instance`` (the CSR rows expanded)."""
        return np.repeat(np.arange(self.n_poses), np.diff(self.view_ptr))

    @functools.cached_property
    def visible_matrix_csr(self) -> tuple[np.ndarray, np.ndarray]:
        """(pose, instance) pairs of the success rule, as two aligned arrays."""
        return self.view_pose[self.view_visible], self.view_instance[self.view_visible]

    def goal_mask(self, object_type: str) -> np.ndarray:
        """Bool ``[P]``: poses where some instance of ``object_type`` is visible."""
        return self.goal_mask_for_instances(self.instances_of(object_type))

    def goal_mask_for_instances(self, instances: np.ndarray) -> np.ndarray:
        poses, inst = self.visible_matrix_csr
        mask = np.zeros(self.n_poses, dtype=bool)
        mask[poses[np.isin(inst, instances)]] = True
        return mask

    def in_frame_mask_for_instances(self, instances: np.ndarray) -> np.ndarray:
        """Bool ``[P]``: poses with one of ``instances`` in the frame at any distance (a superset of
        :meth:`goal_mask_for_instances`'s poses)."""
        mask = np.zeros(self.n_poses, dtype=bool)
        mask[self.view_pose[np.isin(self.view_instance, instances)]] = True
        return mask

    @functools.cached_property
    def predecessors(self) -> list[np.ndarray]:
        preds: list[list[int]] = [[] for _ in range(self.n_poses)]
        for p, row in enumerate(self.successors):
            for q in set(row.tolist()) - {p}:
                preds[q].append(p)
        return [np.asarray(sorted(x), dtype=np.int64) for x in preds]

    @functools.cached_property
    def _predecessor_csr(self) -> tuple[np.ndarray, np.ndarray]:
        """:attr:`predecessors` as CSR arrays ``(indptr [P + 1], indices)``."""
        counts = np.fromiter((len(p) for p in self.predecessors), dtype=np.int64, count=self.n_poses)
        indptr = np.concatenate([[0], np.cumsum(counts)])
        indices = np.concatenate(self.predecessors) if self.n_poses else np.zeros(0, np.int64)
        return indptr, indices.astype(np.int64, copy=False)

    @functools.cached_property
    def components(self) -> np.ndarray:
        """``[P]`` label of each pose's strongly connected component of the pose graph, numbered by
        size (0: the largest; ties by lowest pose id). The built-in scenes' reachable grid is a
        union of several sources, and in a few scenes it leaves islands cut off from the rest."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        src = np.repeat(np.arange(self.n_poses), self.successors.shape[1])
        dst = self.successors.reshape(-1)
        graph = coo_matrix((np.ones(len(src), np.int8), (src, dst)), shape=(self.n_poses,) * 2)
        _, raw = connected_components(graph.tocsr(), directed=True, connection="strong")
        sizes = np.bincount(raw)
        first = np.full(len(sizes), self.n_poses)
        np.minimum.at(first, raw, np.arange(self.n_poses))
        order = np.lexsort((first, -sizes))  # largest first, then by first pose
        rank = np.empty(len(sizes), dtype=np.int64)
        rank[order] = np.arange(len(sizes))
        return rank[raw]

    @functools.cached_property
    def usable_poses(self) -> np.ndarray:
        """Bool ``[P]``: poses of the components an agent can use, where episodes may start.

        The references generate their data by BFS from one start, so every pose of theirs lies in
        one component. Here a component counts when it holds at least ``USABLE_COMPONENT_SHARE`` of
        the largest one's poses: the islands of one or two positions (16 or 32 poses) that the
        union of reachable-grid sources leaves in a few scenes are left out, while both halves of
        FloorPlan29 (768 and 624 poses) are kept: each is a real standing area (ALFRED's AI2-THOR
        2.1 layout holds 35 and 30 of its positions, the rearrangement-2023 AI2-THOR 5 agent starts
        24 and 18) and no source links them. A start must in addition reach its target (samplers
        check that per target)."""
        sizes = np.bincount(self.components)
        usable = sizes >= USABLE_COMPONENT_SHARE * sizes.max() if len(sizes) else sizes.astype(bool)
        return usable[self.components]

    def distances_to(self, goal: np.ndarray) -> np.ndarray:
        """Reverse BFS: number of movement actions from every pose to the nearest goal pose
        (-1 where unreachable). The optimal episode length (SAVN convention) is this + 1 (Done).

        Level by level over the whole frontier at once (array operations, not a queue of poses): a
        training sampler meets every target of every scene once, and a queue in Python took ~7 ms
        per target, a tenth of a short benchmark's time."""
        dist = np.full(self.n_poses, -1, dtype=np.int32)
        frontier = np.flatnonzero(goal)
        dist[frontier] = 0
        indptr, indices = self._predecessor_csr
        degree = np.diff(indptr)
        level = 0
        while frontier.size:
            level += 1
            starts, counts = indptr[frontier], degree[frontier]
            offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
            reached = indices[np.repeat(starts, counts) + offsets]
            frontier = np.unique(reached[dist[reached] < 0])
            dist[frontier] = level
        return dist

    def target_distances(self, object_type: str) -> np.ndarray:
        if object_type not in self._distance_cache:
            self._distance_cache[object_type] = self.distances_to(self.goal_mask(object_type))
        return self._distance_cache[object_type]

    def optimal_length(self, start: int, object_type: str) -> int:
        """Optimal episode length in actions including ``Done`` (-1 if unreachable)."""
        d = int(self.target_distances(object_type)[start])
        return d + 1 if d >= 0 else -1
