"""Assertions shared by the offline and thor tests: two SceneData describe the same scene."""

from __future__ import annotations

import numpy as np

from mapless.sim.scene_data import SceneData


def visible_ids(sd: SceneData, pose: int) -> set[str]:
    return {sd.instance_ids[i] for i in sd.visible(pose)}


def boxes_by_type(sd: SceneData, pose: int) -> dict[str, list[tuple[float, ...]]]:
    s = slice(sd.view_ptr[pose], sd.view_ptr[pose + 1])
    out: dict[str, list[tuple[float, ...]]] = {}
    for i, box in zip(sd.view_instance[s], sd.view_box[s], strict=True):
        out.setdefault(sd.instance_types[i], []).append(tuple(box.tolist()))
    return {t: sorted(b) for t, b in out.items()}


def visible_boxes(sd: SceneData, pose: int) -> dict[str, tuple[float, ...]]:
    s = slice(sd.view_ptr[pose], sd.view_ptr[pose + 1])
    return {
        sd.instance_ids[i]: tuple(b.tolist())
        for i, b, v in zip(sd.view_instance[s], sd.view_box[s], sd.view_visible[s], strict=True)
        if v
    }


def assert_same_scene(original: SceneData, read: SceneData, features: bool = True) -> None:
    """Identical transitions, visibility, boxes, shortest paths (and context, features)."""
    assert read.n_poses == original.n_poses
    keys = [original.key(p) for p in range(original.n_poses)]
    order = np.array([read.pose_index[k] for k in keys])  # read pose of each original pose
    inverse = np.argsort(order)
    np.testing.assert_array_equal(inverse[read.successors[order]], original.successors)
    for p in range(original.n_poses):
        q = order[p]
        assert visible_ids(read, q) == visible_ids(original, p), keys[p]
        assert boxes_by_type(read, q) == boxes_by_type(original, p), keys[p]
        assert visible_boxes(read, q) == visible_boxes(original, p), keys[p]
    visible_types = {original.instance_types[i] for i in original.visible_matrix_csr[1]}
    for object_type in sorted(visible_types):
        np.testing.assert_array_equal(
            read.target_distances(object_type)[order],
            original.target_distances(object_type),
            err_msg=object_type,
        )
    for object_id in {original.instance_ids[i] for i in original.visible_matrix_csr[1]}:
        goal_o = original.goal_mask_for_instances(np.array([original.instance_ids.index(object_id)]))
        goal_r = read.goal_mask_for_instances(np.array([read.instance_ids.index(object_id)]))
        np.testing.assert_array_equal(read.distances_to(goal_r)[order], original.distances_to(goal_o))
    np.testing.assert_allclose(read.context[order], original.context, atol=1e-6)
    if features:
        assert read.features.dtype == original.features.dtype
        np.testing.assert_array_equal(read.features[order], original.features)
        assert read.feature_scale == original.feature_scale
