"""The live backend against a real AI2-THOR (needs the Unity build, so it is not part of the
default suite: without ``MAPLESS_THOR=1`` pytest reports these tests as skipped, with the reason).

Run with ``MAPLESS_THOR=1 pytest tests/test_thor_real.py`` on a machine with ``mapless[thor]``
installed and a display (or ``MAPLESS_THOR_PLATFORM=CloudRendering`` for headless Vulkan).
The first run downloads the Unity build (~500 MB).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from mapless.actions import N_MOVEMENT_ACTIONS
from mapless.offline import load_offline_scene

pytestmark = pytest.mark.skipif(
    os.environ.get("MAPLESS_THOR") != "1",
    reason="live AI2-THOR (the Unity build and a display): opt in with MAPLESS_THOR=1",
)


@pytest.fixture(scope="module")
def controller():
    from mapless.thor import ThorConfig, make_controller

    config = ThorConfig(platform=os.environ.get("MAPLESS_THOR_PLATFORM"))
    controller = make_controller("FloorPlan420", config)
    yield controller, config
    controller.stop()


def test_live_steps(controller):
    from mapless.thor import LiveThorScene

    live = LiveThorScene(*controller)
    obs = live.reset("FloorPlan420")
    assert obs["context"].shape[1] == 4 and obs["features"].shape[1:] == (7, 7)
    for action in (1, 1, 0, 4, 3, 2, 0):
        obs, _ = live.step(action)
        assert set(obs["visible_ids"]) <= set(obs["in_view_ids"])


def test_scrape_smallest_scene(controller, tmp_path):
    from mapless.thor import scrape

    folder = scrape(controller[0], "FloorPlan420", tmp_path, "savn", controller[1])
    sd = load_offline_scene(folder)
    assert sd.n_poses > 100 and sd.visible_matrix_csr[0].size > 0
    moved = sd.successors != np.arange(sd.n_poses)[:, None]
    assert moved[:, 1:3].all() and moved[:, 0].any() and moved.shape[1] == N_MOVEMENT_ACTIONS
