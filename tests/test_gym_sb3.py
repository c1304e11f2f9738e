"""``mapless/ObjectNav-v0`` as other tools use it: made with no argument after ``import mapless``,
its keyword options, top-down frames, infos that neither collide with the wrappers' keys nor change
after the step that returned them, vector environments, gymnasium's and stable-baselines3's
environment checkers, and a short PPO run of stable-baselines3 under gymnasium's episode
statistics (the wrapper every CleanRL script uses)."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch

import mapless
from mapless.actions import DONE
from mapless.episodes.objectnav import fixed_episodes, scene_library
from mapless.errors import MaplessError
from mapless.scenes.catalogue import scene_names
from mapless.scenes.categories import targets
from mapless.sim.episode import Episode
from mapless.sim.pictures import _AGENT_RGB, _GOAL_RGB

#: A small kitchen and a small bathroom: two room types for the sampler, seconds to build.
SCENES = "FloorPlan25,FloorPlan425"


@pytest.fixture(scope="module")
def library():
    return scene_library()


@pytest.mark.slow
def test_the_id_needs_no_argument_and_samples_training_episodes_on_the_training_scenes():
    env = gym.make(mapless.ENV_ID)
    assert env.spec.id == "mapless/ObjectNav-v0"
    _, info = env.reset(seed=0)
    episode = info["mapless_episode"]
    assert episode.scene in scene_names("train")
    assert episode.target in targets("mjolnir22")[env.unwrapped.data.room_type]
    assert env.unwrapped.max_steps == 30  # training episodes' limit
    env.close()


def test_scenes_episodes_and_protocol_are_keyword_options():
    sampled = gym.make(mapless.ENV_ID, scenes="train:bathroom").unwrapped
    assert sampled.sampler.room_cycle == ["bathroom"] and sampled.protocol.name == "standard"
    # The protocol decides the success rule of the scenes and the sets read by name.
    reference = gym.make(mapless.ENV_ID, episodes="test", protocol="reference").unwrapped
    assert (
        reference.episodes
        == fixed_episodes("test", "reference")
        == fixed_episodes("test", "reference", "hoz22")
    )
    assert reference.protocol.visibility_distance == 1.5
    assert reference.sampler is None and reference.mode == "eval"
    standard = gym.make(mapless.ENV_ID, episodes="val").unwrapped
    assert standard.episodes[0].scene in scene_names("val")
    assert reference.episodes[0] not in standard.episodes
    # The reference protocol's sampled episodes are of the published episodes' classes.
    assert gym.make(mapless.ENV_ID, protocol="reference").unwrapped.sampler.targets == targets("hoz22")
    with pytest.raises(KeyError, match="protocol"):
        gym.make(mapless.ENV_ID, protocol="nope")


def test_a_shared_library_must_count_success_as_the_protocol_does(library):
    assert library.sim.visibility_distance == 1.0  # scene_library(): the standard rule
    with pytest.raises(MaplessError, match=r"within 1.0 m, the reference protocol within 1.5 m"):
        gym.make(mapless.ENV_ID, protocol="reference", library=library)
    with pytest.raises(MaplessError, match="give library or cache_dir"):
        gym.make(mapless.ENV_ID, library=library, cache_dir="elsewhere")
    same = gym.make(mapless.ENV_ID, protocol="paper", library=library).unwrapped  # the paper's rule is 1.0 m
    assert same.library is library


def test_a_seeded_reset_restarts_the_episode_stream(library):
    env = gym.make(mapless.ENV_ID, scenes=SCENES, library=library)
    first = [env.reset(seed=5)[1]["mapless_episode"]] + [env.reset()[1]["mapless_episode"] for _ in range(3)]
    again = [env.reset(seed=5)[1]["mapless_episode"]] + [env.reset()[1]["mapless_episode"] for _ in range(3)]
    assert first == again
    assert {e.scene for e in first} == {"FloorPlan25", "FloorPlan425"}  # the room cycle alternates


def test_infos_keep_off_the_wrappers_keys_and_never_change_afterwards(library):
    data = library["FloorPlan25"]
    start = int(np.flatnonzero(data.horizon == 0)[0])
    env = gym.make(
        mapless.ENV_ID, episodes=[Episode("FloorPlan25", "Toaster", data.pose_tuple(start))], library=library
    )
    _, first = env.reset(seed=0)
    infos = [first] + [env.step(action)[4] for action in (1, 0, 0, 2, 0)]
    assert all("episode" not in info for info in infos)
    assert [len(info["visited"]) for info in infos] == [1, 2, 3, 4, 5, 6]
    assert infos[0]["visited"] == (start,) and infos[-1]["visited"][:1] == (start,)
    assert all(info["visited"][-1] == info["pose"] for info in infos)
    assert all(isinstance(info["mapless_episode"], Episode) for info in infos)


def test_rgb_array_frames_show_the_agent_where_it_stands_and_where_the_target_is_seen(library):
    data = library["FloorPlan25"]
    start = int(np.flatnonzero(data.horizon == 0)[0])
    episode = Episode("FloorPlan25", "Toaster", data.pose_tuple(start))
    env = gym.make(mapless.ENV_ID, episodes=[episode], library=library, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (256, 256, 3) and frame.dtype == np.uint8
    painter = env.unwrapped._frames["FloorPlan25"]

    def pixel(pose: int) -> np.ndarray:
        row, col = painter._pixel(data.x[pose], data.z[pose])
        return frame[int(row), int(col)]

    assert (pixel(start) == _AGENT_RGB).all()
    seen_from = np.flatnonzero(
        data.goal_mask(episode.target) & (np.hypot(data.x - data.x[start], data.z - data.z[start]) > 0.5)
    )
    assert len(seen_from) and (pixel(int(seen_from[0])) == _GOAL_RGB).all()
    before = frame
    pose = env.unwrapped.pose
    while env.unwrapped.pose == pose:  # turn until a move succeeds
        env.step(0 if env.unwrapped.steps % 2 == 0 else 1)
    frame = env.render()
    assert not np.array_equal(frame, before) and (pixel(env.unwrapped.pose) == _AGENT_RGB).all()
    with pytest.raises(MaplessError, match="render_mode"):
        gym.make(mapless.ENV_ID, episodes=[episode], library=library, render_mode="ansi")


def test_a_vector_environment_shares_one_scene_library_and_resets_finished_copies(library):
    envs = mapless.make_vec_env(3, scenes=SCENES, library=library)
    assert isinstance(envs, gym.vector.SyncVectorEnv)
    assert all(env.unwrapped.library is library for env in envs.envs)
    obs, _ = envs.reset(seed=0)
    assert obs["features"].shape == (3, 104, 7, 7) and obs["target_index"].shape == (3, 1)
    _, _, terminated, _, _ = envs.step(np.full(3, DONE))
    assert terminated.all()
    envs.close()
    with pytest.raises(MaplessError, match="at least one"):
        mapless.make_vec_env(0)


def test_gymnasium_and_sb3_checkers_pass_and_ppo_trains_under_episode_statistics(
    library, single_torch_thread
):
    from gymnasium.utils.env_checker import check_env as gymnasium_check
    from gymnasium.wrappers import RecordEpisodeStatistics
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_checker import check_env as sb3_check

    env = RecordEpisodeStatistics(
        gym.make(mapless.ENV_ID, scenes=SCENES, library=library, render_mode="rgb_array")
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # advice on unbounded boxes and non-image 3-d arrays
        gymnasium_check(env.unwrapped)
        sb3_check(env)
    model = PPO("MultiInputPolicy", env, n_steps=64, batch_size=64, n_epochs=2, seed=0, device="cpu")
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(total_timesteps=256)
    assert model.num_timesteps == 256
    assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters(), strict=True))
    # Training episodes last at most 30 steps, so 256 steps finish several, each one recorded.
    assert len(env.return_queue) >= 256 // 30
    assert all(length <= 30 for length in env.length_queue)
