"""Camera projection, ray casting, occlusion, distances and closed receptacles on known geometry."""

from __future__ import annotations

import numpy as np
import pytest

from mapless.errors import MaplessError
from mapless.sim.build import build_scene_data, build_transitions
from mapless.sim.camera import camera_basis, project
from mapless.sim.config import SimConfig
from mapless.sim.raycast import FLOOR, WALL, RayCaster
from mapless.sim.room import InteriorMask
from tests.synthetic import box, square_room

CONFIG = SimConfig(ray_resolution=84)


def render(scene, x, z, yaw, horizon, config=CONFIG):
    walls = InteriorMask(scene, config.wall_clearance).wall_distances(np.array([[x, z]]))[0]
    return RayCaster(scene, config).render(x, z, yaw, horizon, walls)


def test_camera_basis_follows_unity_conventions():
    forward, right, up = camera_basis(0, 0)
    np.testing.assert_allclose(forward, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(right, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(up, [0, 1, 0], atol=1e-12)
    forward, right, _ = camera_basis(90, 0)  # yaw is clockwise from +z seen from above: 90 = +x
    np.testing.assert_allclose(forward, [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(right, [0, 0, -1], atol=1e-12)
    forward, _, _ = camera_basis(0, 30)  # positive horizon looks down
    np.testing.assert_allclose(forward, [0, -0.5, np.sqrt(3) / 2], atol=1e-12)


def test_projection_of_known_points():
    eye = np.array([0.0, 1.5, 0.0])
    points = np.array([[0.0, 1.5, 2.0], [2.0, 1.5, 2.0], [0.0, 3.5, 2.0], [0.0, 1.5, -1.0]])
    pixels, depth = project(points, eye, 0, 0, 90.0, 300)
    np.testing.assert_allclose(pixels[0], [150, 150], atol=1e-9)  # straight ahead: image centre
    np.testing.assert_allclose(pixels[1], [300, 150], atol=1e-9)  # 45 degrees right: right edge (90 deg FOV)
    np.testing.assert_allclose(pixels[2], [150, 0], atol=1e-9)  # 45 degrees up: top edge
    assert depth[3] < 0  # behind the camera


def test_box_in_front_has_the_projected_pixel_box():
    # A 1 m wide, 1 m tall box centred 2 m ahead at eye height spans +-atan(0.5/1.5)... in x:
    # its front face at z = 1.5 projects to 150 +- 0.5/1.5 * 150 = [100, 200].
    eye_height = CONFIG.eye_height
    scene = square_room([box("Box|1", "Box", (0, eye_height, 2.0), (1.0, 1.0, 1.0))], half_width=4)
    frame = render(scene, 0.0, 0.0, 0, 0)
    res = CONFIG.ray_resolution
    hit = np.flatnonzero(frame.ids == 0)
    cols, rows = hit % res, hit // res
    scale = 300 / res
    assert cols.min() * scale == pytest.approx(100, abs=scale)
    assert (cols.max() + 1) * scale == pytest.approx(200, abs=scale)
    assert rows.min() * scale == pytest.approx(100, abs=scale)
    # The centre ray hits the front face at 1.5 m.
    centre = (res // 2) * res + res // 2
    assert frame.depth[centre] == pytest.approx(1.5, abs=0.02)


def test_floor_and_walls_bound_every_ray():
    scene = square_room([], half_width=2.0)
    frame = render(scene, 0.0, 0.0, 0, 30)
    assert set(np.unique(frame.ids)) <= {FLOOR, WALL}
    floor_rays = frame.ids == FLOOR
    np.testing.assert_allclose(frame.points[floor_rays, 1], 0.0, atol=1e-9)
    # Walls stand at most at the floor edge (z = 2) plus the tabulation resolution.
    assert frame.points[~floor_rays, 2].max() <= 2.0 + 0.03


@pytest.mark.slow
def test_occluded_object_is_not_in_view_and_partial_occlusion_shrinks_its_box():
    h = CONFIG.eye_height
    front = box("Wall|1", "Cabinet", (0, h, 1.5), (2.0, 2.0, 0.2))  # wide, covers the view of the apple
    hidden = box("Apple|1", "Apple", (0, h, 2.5), (0.2, 0.2, 0.2), pickupable=True)
    scene = square_room([front, hidden], half_width=4)
    data = build_scene_data(scene, CONFIG)
    pose = data.pose_index["0.00|0.00|0|0"]
    apple = scene.object_index["Apple|1"]
    assert apple not in data.in_view(pose)
    # Half-occluded: the blocker covers x < 0 only; the far box spans x in [-0.5, 0.5].
    blocker = box("Cab|1", "Cabinet", (-1.0, h, 1.0), (2.0, 2.0, 0.2))
    far = box("Fridge|1", "Fridge", (0, h, 3.0), (1.0, 1.0, 0.2))
    data = build_scene_data(square_room([blocker, far], half_width=4), CONFIG)
    pose = data.pose_index["0.00|0.00|0|0"]
    entries = slice(data.view_ptr[pose], data.view_ptr[pose + 1])
    boxes = dict(zip(data.view_instance[entries].tolist(), data.view_box[entries], strict=True))
    fridge = 1  # index of the far box in the scene's object list
    assert fridge in boxes
    x1, _, x2, _ = boxes[fridge]
    # Unoccluded it would span 150 +- 0.5/2.9*150 = [124, 176]; the left half is hidden behind x < 0.
    assert x1 >= 150 - 300 / 84 and x2 == pytest.approx(176, abs=4)


@pytest.mark.slow
def test_visibility_distance_uses_the_vertical_capsule():
    # Apple on the floor 0.9 m ahead: seen looking down, horizontal distance 0.9 -> visible at 1.0 m.
    near = box("Apple|1", "Apple", (0, 0.05, 0.9), (0.1, 0.1, 0.1), pickupable=True)
    far = box("Mug|1", "Mug", (0.3, 0.05, 1.4), (0.1, 0.1, 0.1), pickupable=True)
    data = build_scene_data(square_room([near, far], half_width=3), CONFIG)
    pose = data.pose_index["0.00|0.00|0|30"]
    assert set(data.in_view(pose).tolist()) == {0, 1}
    assert set(data.visible(pose).tolist()) == {0}
    entries = slice(data.view_ptr[pose], data.view_ptr[pose + 1])
    distance = dict(zip(data.view_instance[entries].tolist(), data.view_distance[entries], strict=True))
    assert distance[0] == pytest.approx(0.85, abs=0.05)  # nearest visible face of the apple
    wider = build_scene_data(square_room([near, far], half_width=3), SimConfig(visibility_distance=1.5))
    assert set(wider.visible(pose).tolist()) == {0, 1}


@pytest.mark.slow
def test_contents_of_closed_receptacles_are_never_visible_but_open_shelves_show_theirs():
    h = 1.0
    fridge = box("Fridge|1", "Fridge", (0, h, 1.0), (0.8, 2.0, 0.6), receptacle=True, openable=True)
    inside = box("Apple|1", "Apple", (0, h, 1.0), (0.1, 0.1, 0.1), pickupable=True, parents=("Fridge|1",))
    data = build_scene_data(square_room([fridge, inside], half_width=3), CONFIG)
    assert not data.view_visible[data.view_instance == 1].any()
    shelf = box("Shelf|1", "Shelf", (0, h, 1.0), (0.8, 2.0, 0.6), receptacle=True)
    vase = box("Vase|1", "Vase", (0, h, 0.95), (0.2, 0.2, 0.2), pickupable=True, parents=("Shelf|1",))
    data = build_scene_data(square_room([shelf, vase], half_width=3), CONFIG)
    pose = data.pose_index["0.00|0.00|0|0"]
    vase_index = 1
    assert vase_index in data.visible(pose).tolist()


def test_transitions_diagonal_moves_walls_and_obstacles():
    table = box("Table|1", "DiningTable", (0.5, 0.4, 0.0), (0.4, 0.8, 0.4))
    scene = square_room([table], half_width=2.0)
    # Reachable grid points under the table would not exist in real data; remove them here too.
    keep = ~((np.abs(scene.reachable[:, 0] - 0.5) < 0.2) & (np.abs(scene.reachable[:, 1]) < 0.2))
    scene = square_room([table], half_width=2.0).__class__(
        **{**scene.__dict__, "reachable": scene.reachable[keep]}
    )
    config = SimConfig()
    succ = build_transitions(scene, config)
    data_keys = {}
    n_yaw, n_hor = 8, 2
    for p, (x, z) in enumerate(scene.reachable):
        for y in range(n_yaw):
            for h in range(n_hor):
                data_keys[(round(x, 2), round(z, 2), y * 45, h * 30)] = (p * n_yaw + y) * n_hor + h

    def pose(x, z, yaw, hor=0):
        return data_keys[(x, z, yaw, hor)]

    assert succ[pose(0.0, 0.0, 0), 0] == pose(0.0, 0.25, 0)  # north
    assert succ[pose(0.0, 0.0, 45), 0] == pose(0.25, 0.25, 45)  # diagonal: (+0.25, +0.25)
    assert succ[pose(0.0, 0.0, 225), 0] == pose(-0.25, -0.25, 225)
    assert succ[pose(1.5, 1.5, 0), 0] == pose(1.5, 1.5, 0)  # grid edge: fails, pose unchanged
    assert succ[pose(0.25, 0.0, 90), 0] == pose(0.25, 0.0, 90)  # (0.5, 0) is under the table
    # Diagonal from (0.25, 0.25) to (0.5, 0.5)... passes the table corner at (0.3..0.7, -0.2..0.2)? no:
    assert succ[pose(0.25, 0.25, 135), 0] == pose(0.25, 0.25, 135)  # to (0.5, 0.0): removed point
    assert succ[pose(0.0, 0.0, 0), 1] == pose(0.0, 0.0, 315)  # RotateLeft wraps
    assert succ[pose(0.0, 0.0, 315), 2] == pose(0.0, 0.0, 0)
    assert succ[pose(0.0, 0.0, 0, 0), 3] == pose(0.0, 0.0, 0, 0)  # LookUp at 0 fails
    assert succ[pose(0.0, 0.0, 0, 0), 4] == pose(0.0, 0.0, 0, 30)
    assert succ[pose(0.0, 0.0, 0, 30), 4] == pose(0.0, 0.0, 0, 30)  # LookDown at 30 fails


def test_segment_crossing_an_obstacle_blocks_a_move_between_reachable_points():
    # A thin obstacle between two grid points that are both reachable.
    post = box("Post|1", "FloorLamp", (0.125, 0.8, 0.125), (0.3, 1.6, 0.3))
    scene = square_room([post], half_width=2.0)
    config = SimConfig(obstacle_margin=0.05)
    succ = build_transitions(scene, config)
    keys = {(round(x, 2), round(z, 2)): p for p, (x, z) in enumerate(scene.reachable)}
    p = keys[(0.0, 0.0)]
    diagonal = (p * 8 + 1) * 2  # yaw 45, horizon 0
    assert succ[diagonal, 0] == diagonal  # the diagonal to (0.25, 0.25) crosses the post
    north = (p * 8 + 0) * 2
    assert succ[north, 0] != north


@pytest.mark.parametrize(
    ("setting", "value"),
    [
        ("grid_size", 0.5),
        ("rotation_step", 30),
        ("ray_resolution", 80),
        ("horizons", ()),
        ("horizontal_fov", 180),
    ],
)
def test_settings_the_simulator_cannot_honour_are_refused(setting, value):
    with pytest.raises(MaplessError, match=f"sim.{setting} = .*: must be"):
        SimConfig(**{setting: value})


def test_strict_diagonals_refuse_to_cut_a_corner():
    import dataclasses

    # An L of three grid points: (0, 0) -> (0.25, 0.25) at yaw 45 passes (0.25, 0), on the grid,
    # and (0, 0.25), off it: a corner. SAVN's rule moves; the strict rule does not.
    scene = dataclasses.replace(square_room([]), reachable=np.array([[0.0, 0.0], [0.25, 0.0], [0.25, 0.25]]))
    loose = build_transitions(scene, CONFIG)
    strict = build_transitions(scene, SimConfig(strict_diagonals=True))
    n_yaw, n_hor = len(CONFIG.yaws), len(CONFIG.horizons)
    pose = (0 * n_yaw + CONFIG.yaws.index(45)) * n_hor  # position 0, yaw 45, horizon 0
    assert loose[pose, 0] == (2 * n_yaw + CONFIG.yaws.index(45)) * n_hor and strict[pose, 0] == pose
    # Only the corner's two diagonal steps change, out of 0 at yaw 45 and back out of 2 at yaw 225.
    differ = sorted({int(p) for p in np.flatnonzero((loose != strict).any(axis=1))})
    corner = [
        (p * n_yaw + CONFIG.yaws.index(y)) * n_hor + h for p, y in ((0, 45), (2, 225)) for h in range(n_hor)
    ]
    assert differ == sorted(corner) and (loose[differ, 1:] == strict[differ, 1:]).all()
