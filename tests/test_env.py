"""The gymnasium and batched environments on a real floor plan: rewards, termination, BFS lengths,
parent reward, equivalence of the two forms, and bad-input errors."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from mapless import ENV_ID
from mapless.actions import DONE
from mapless.episodes import Episode
from mapless.errors import MaplessError
from mapless.sim.env import NavEnv
from mapless.sim.library import SceneLibrary
from mapless.sim.task import RewardConfig
from mapless.sim.vector import BatchedNavEnv

SCENE = "FloorPlan25"  # a small kitchen (47 grid points)


@pytest.fixture(scope="module")
def library() -> SceneLibrary:
    return SceneLibrary.builtin()


def far_episode(library, target="Toaster") -> tuple[Episode, int]:
    data = library[SCENE]
    distances = data.target_distances(target)
    pose = int(np.argmax(np.where(data.horizon == 0, distances, -1)))
    return Episode(SCENE, target, data.pose_tuple(pose)), pose


def test_distances_are_those_of_a_pose_by_pose_bfs(library):
    """The level-at-once BFS against the textbook queue over the successor graph, for every instance
    of the scene as the goal, all of them together, and none."""
    from collections import deque

    data = library[SCENE]
    into: dict[int, set[int]] = {q: set() for q in range(data.n_poses)}
    for p in range(data.n_poses):
        for q in data.successors[p]:
            if q != p:
                into[int(q)].add(p)

    def queue_bfs(goal):
        dist = np.full(data.n_poses, -1)
        queue = deque(np.flatnonzero(goal))
        dist[list(queue)] = 0
        while queue:
            q = queue.popleft()
            for p in into[int(q)]:
                if dist[p] < 0:
                    dist[p] = dist[q] + 1
                    queue.append(p)
        return dist

    goals = [data.goal_mask_for_instances(np.array([i])) for i in np.unique(data.view_instance)]
    goals += [np.ones(data.n_poses, dtype=bool), np.zeros(data.n_poses, dtype=bool)]
    for goal in goals:
        np.testing.assert_array_equal(data.distances_to(goal), queue_bfs(goal))


def optimal_actions(data, pose: int, target: str) -> list[int]:
    """Greedy descent of the BFS distance field, then Done."""
    distances = data.target_distances(target)
    actions = []
    while distances[pose] > 0:
        action = int(
            np.argmin([distances[q] if distances[q] >= 0 else 1 << 30 for q in data.successors[pose]])
        )
        pose = int(data.successors[pose, action])
        actions.append(action)
    return [*actions, DONE]


def test_following_the_bfs_path_succeeds_in_exactly_the_optimal_length(library):
    episode, pose = far_episode(library)
    env = NavEnv(library, [episode])
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    actions = optimal_actions(library[SCENE], pose, "Toaster")
    assert info["optimal_length"] == len(actions) >= 5
    total = 0.0
    for i, action in enumerate(actions):
        obs, reward, terminated, truncated, info = env.step(action)
        total += reward
        assert terminated == (i == len(actions) - 1) and not truncated
    assert info["success"]
    assert total == pytest.approx(5.0 - 0.01 * (len(actions) - 1))
    assert len(info["visited"]) == len(actions)  # start + every movement


def test_done_away_from_the_target_fails_and_step_limit_truncates(library):
    episode, _ = far_episode(library)
    env = NavEnv(library, [episode])
    env.reset(seed=0)
    _, reward, terminated, truncated, info = env.step(DONE)
    assert terminated and not truncated and not info["success"] and reward == pytest.approx(-0.01)
    env.reset()
    for step in range(30):
        _, _, terminated, truncated, _ = env.step(1)  # rotate in place
        assert not terminated and truncated == (step == 29)
    evaluation = NavEnv(library, [episode], mode="eval")
    evaluation.reset()
    assert evaluation.max_steps == 100  # kitchens; 200 in living rooms


def test_failed_moves_leave_the_pose_unchanged(library):
    data = library[SCENE]
    blocked = np.flatnonzero(data.successors[:, 0] == np.arange(data.n_poses))
    pose = int(blocked[0])
    env = NavEnv(library, [Episode(SCENE, "Toaster", data.pose_tuple(pose))])
    env.reset()
    _, _, _, _, info = env.step(0)
    assert info["failed_action"] and info["pose"] == pose


def test_gymnasium_make_and_registered_id(library):
    episode, _ = far_episode(library)
    env = gym.make(ENV_ID, library=library, episodes=[episode])
    obs, _ = env.reset(seed=1)
    assert obs["context"].shape == (101, 4) and obs["features"].shape == (104, 7, 7)
    # One element, not a 0-d array: stable-baselines3's policies refuse 0-d observations.
    assert obs["target_index"].shape == (1,)
    assert obs["target_index"][0] == env.unwrapped.targets.categories.type_to_index[episode.target]
    env.close()


def test_batched_env_matches_the_single_env(library):
    data = library[SCENE]
    rng = np.random.default_rng(3)
    starts = rng.choice(np.flatnonzero(data.horizon == 0), size=8, replace=False)
    targets = ["Toaster", "Mug", "Apple", "Bread"]
    episodes = [Episode(SCENE, targets[i % 4], data.pose_tuple(int(p))) for i, p in enumerate(starts)]
    actions = rng.integers(0, 6, size=(30, 8))
    rewards = RewardConfig(parent_reward=True)
    batched = BatchedNavEnv(library, [SCENE], 8, rewards=rewards)
    batched.reset(np.arange(8), episodes)
    for slot, episode in enumerate(episodes):
        env = NavEnv(library, [episode], rewards=rewards)
        obs, info = env.reset()
        assert batched.optimal_length[slot] == info["optimal_length"]
        np.testing.assert_array_equal(batched.observe()["context"][slot], obs["context"])
    singles = [NavEnv(library, [e], rewards=rewards) for e in episodes]
    for env in singles:
        env.reset()
    finished = np.zeros(8, bool)
    for row in actions:
        step = batched.step(row)
        obs = batched.observe(("context", "features"))
        for slot, env in enumerate(singles):
            if finished[slot]:
                assert not step.active[slot]
                continue
            single_obs, reward, terminated, truncated, info = env.step(row[slot])
            assert step.reward[slot] == pytest.approx(reward)
            assert step.success[slot] == info["success"]
            assert step.terminated[slot] == terminated and step.truncated[slot] == truncated
            np.testing.assert_allclose(obs["features"][slot], single_obs["features"])
            finished[slot] = terminated or truncated


def _seen_categories(data, rule: str) -> np.ndarray:
    """Bool ``[poses, C]`` of the category rows a parent rule counts as seen, from the scene's arrays
    pose by pose: ``in_frame`` the context's in-view column, ``visible`` the success rule's instances."""
    if rule == "in_frame":
        return data.context[:, :, 0] > 0
    from mapless.scenes.categories import category_set

    rows = category_set().type_to_index
    seen = np.zeros(data.context.shape[:2], dtype=bool)
    for pose in range(data.n_poses):
        for instance in data.visible(pose):
            row = rows.get(data.instance_types[instance], -1)
            if row >= 0:
                seen[pose, row] = True
    return seen


def test_context_distance_is_the_nearest_in_view_instance_of_each_category(library):
    """Pose by pose against the scene's in-view lists: per category, the smallest distance of its
    in-view instances, 0 where none is in view (so exactly where the context's in-view flag is 0)."""
    from mapless.scenes.categories import category_set

    data, rows = library[SCENE], category_set().type_to_index
    env = BatchedNavEnv(library, [SCENE], 1)
    distance = env.context_distance
    assert distance.shape == data.context.shape[:2]
    for pose in range(data.n_poses):
        expected = np.zeros(data.context.shape[1], dtype=np.float32)
        s = slice(data.view_ptr[pose], data.view_ptr[pose + 1])
        for instance, d in zip(data.view_instance[s], data.view_distance[s], strict=True):
            row = rows.get(data.instance_types[instance], -1)
            if row >= 0:
                expected[row] = d if expected[row] == 0 else min(expected[row], d)
        np.testing.assert_array_equal(distance[pose], expected)
    assert ((distance > 0) == (data.context[:, :, 0] > 0)).all()
    assert distance.max() > 1.5  # in the frame beyond the success rule's reach


@pytest.mark.parametrize("rule", ["visible", "in_frame"])
def test_parent_reward_pays_once_per_parent_per_episode(library, rule):
    data = library[SCENE]
    rewards = RewardConfig(parent_reward=True, parent_reward_rule=rule)
    probe = NavEnv(library, [far_episode(library)[0]], rewards=rewards)
    probe.reset()
    weights = probe.batched.parent_weights[0]  # the rules, and their state, are the batched env's
    is_parent = weights > 0
    assert is_parent.any()  # the Toaster has parents in kitchens
    in_view = _seen_categories(data, rule)
    turn_right = data.successors[:, 2]
    # A pose that sees no parent, whose right turn brings one into view.
    candidates = np.flatnonzero(~(in_view & is_parent).any(1) & (in_view[turn_right] & is_parent).any(1))
    pose = int(candidates[0])
    env = NavEnv(library, [Episode(SCENE, "Toaster", data.pose_tuple(pose))], rewards=rewards)
    env.reset()
    _, reward, _, _, _ = env.step(2)
    assert reward == pytest.approx(weights[in_view[turn_right[pose]] & is_parent].max())
    env.step(1)  # back: nothing new in view
    _, again, _, _, _ = env.step(2)
    newly_seen = in_view[turn_right[pose]] & is_parent
    assert again == pytest.approx(-0.01) if newly_seen.sum() == 1 else again <= reward
    env.reset()  # the seen set is per episode: the bonus is paid again
    _, reward_again, _, _, _ = env.step(2)
    assert reward_again == pytest.approx(reward)


def test_a_parent_in_the_frame_beyond_the_visibility_distance_pays_only_under_the_in_frame_rule(library):
    """The default rule is the success rule's visibility (MJOLNIR's ``visible`` flag): a parent in the
    frame but too far away is not yet seen."""
    data = library[SCENE]
    assert RewardConfig().parent_reward_rule == "visible"
    probe = NavEnv(library, [far_episode(library)[0]], rewards=RewardConfig(parent_reward=True))
    probe.reset()
    is_parent = probe.batched.parent_weights[0] > 0
    in_frame, visible = _seen_categories(data, "in_frame"), _seen_categories(data, "visible")
    assert not (visible & ~in_frame).any()  # visible implies in the frame
    turn_right = data.successors[:, 2]
    # A turn that brings a parent into the frame, none of them visible, from a pose seeing none.
    far_only = (
        ~(in_frame & is_parent).any(1)
        & (in_frame[turn_right] & is_parent).any(1)
        & ~(visible[turn_right] & is_parent).any(1)
    )
    pose = int(np.flatnonzero(far_only)[0])
    paid = {}
    for rule in ("visible", "in_frame"):
        rewards = RewardConfig(parent_reward=True, parent_reward_rule=rule)
        env = NavEnv(library, [Episode(SCENE, "Toaster", data.pose_tuple(pose))], rewards=rewards)
        env.reset()
        paid[rule] = env.step(2)[1]
    assert paid["visible"] == pytest.approx(-0.01)
    assert paid["in_frame"] > 0


def test_an_unknown_parent_rule_is_a_config_error():
    from mapless.config import ConfigError

    with pytest.raises(ConfigError, match="parent_reward_rule"):
        RewardConfig(parent_reward_rule="nearby")


def test_off_grid_start_names_the_nearest_valid_pose(library):
    with pytest.raises(MaplessError, match="nearest valid pose"):
        library.pose_of(SCENE, (0.13, 0.02, 0, 0))


def test_parent_reward_can_be_switched_off_per_room_type(library):
    data = library[SCENE]
    rewards = RewardConfig(parent_reward=True, parent_reward_rooms=("bedroom", "bathroom"))
    assert not rewards.pays_parent_reward("kitchen") and rewards.pays_parent_reward("bedroom")
    episode, _ = far_episode(library)
    env = NavEnv(library, [episode], rewards=rewards)
    env.reset()
    paid = [env.step(2)[1] for _ in range(8)]  # a full turn in a kitchen: no parent pays
    assert all(r == pytest.approx(-0.01) for r in paid)
    batched = BatchedNavEnv(library, [SCENE], 1, rewards=rewards)
    batched.reset([0], [episode])
    assert not batched.parent_weights.any() and data.room_type == "kitchen"


def test_episodes_naming_their_instances_aim_at_those_only(library):
    data = library[SCENE]
    toasters = data.instances_of("Toaster")
    assert list(data.goal_instances("Toaster")) == list(toasters)
    named = (data.instance_ids[toasters[0]],)
    assert list(data.goal_instances("Toaster", named)) == [toasters[0]]
    episode, _ = far_episode(library)
    ghost = Episode(episode.scene, episode.target, episode.start, target_ids=(*named, "Toaster|9|9|9"))
    with pytest.raises(MaplessError, match=r"no object Toaster\|9\|9\|9"):
        NavEnv(library, [SCENE]).reset(options={"episode": ghost})
    with pytest.raises(MaplessError, match=r"no object Toaster\|9\|9\|9"):
        BatchedNavEnv(library, [SCENE], 1).reset([0], [ghost])


def test_a_category_set_that_contradicts_the_targets_or_the_scenes_is_refused(library):
    from mapless.sim.task import TargetFields

    episode, _ = far_episode(library)
    all_types, mjolnir = TargetFields("all_types"), TargetFields("mjolnir101")
    for make in (
        lambda **kw: NavEnv(library, episodes=[episode], **kw),
        lambda **kw: BatchedNavEnv(library, [SCENE], 1, **kw),
    ):
        with pytest.raises(MaplessError, match="differs from the given targets"):
            make(targets=all_types, category_set="mjolnir101")
        # The same set twice is fine, and so is either alone.
        assert make(targets=mjolnir, category_set="mjolnir101").targets is mjolnir
        assert make(targets=mjolnir).targets is mjolnir
        assert make(category_set="mjolnir101").targets.category_set_name == "mjolnir101"
    # The built-in scenes have the 101 rows of mjolnir101: all_types' 117 would misread them.
    with pytest.raises(MaplessError, match="117"):
        BatchedNavEnv(library, [SCENE], 1, category_set="all_types")
    env = NavEnv(library, episodes=[episode], targets=all_types)
    with pytest.raises(MaplessError, match="category rows"):
        env.reset(seed=0)


def test_an_episode_naming_its_instances_measures_its_optimal_length_to_them(library):
    data = library[SCENE]
    episode, pose = far_episode(library)
    toasters = data.instances_of("Toaster")
    named = Episode(SCENE, "Toaster", episode.start, target_ids=(data.instance_ids[toasters[-1]],))
    distances = data.distances_to(data.goal_mask_for_instances(toasters[-1:]))
    _, info = NavEnv(library, [named]).reset()
    assert info["optimal_length"] == distances[pose] + 1 >= data.optimal_length(pose, "Toaster")


def test_progress_reward_pays_each_move_toward_the_target(library):
    """On the optimal path every move is one action closer: +weight each, on top of SAVN's rewards."""
    episode, pose = far_episode(library)
    env = NavEnv(library, [episode], rewards=RewardConfig(progress_reward=0.1))
    env.reset(seed=0)
    actions = optimal_actions(library[SCENE], pose, "Toaster")
    total = sum(env.step(action)[1] for action in actions)
    moves = len(actions) - 1
    assert total == pytest.approx(5.0 - 0.01 * moves + 0.1 * moves)


def test_progress_reward_telescopes_to_the_change_of_distance(library):
    """Any walk: shaped minus plain rewards = weight * (distance at the start - distance at the end)."""
    data = library[SCENE]
    distances = data.target_distances("Toaster")
    starts = np.flatnonzero(distances > 0)[:: max(1, int((distances > 0).sum()) // 8)][:8]
    episodes = [Episode(SCENE, "Toaster", data.pose_tuple(int(p))) for p in starts]
    plain = BatchedNavEnv(library, [SCENE], len(episodes), max_steps=20)
    shaped = BatchedNavEnv(
        library, [SCENE], len(episodes), max_steps=20, rewards=RewardConfig(progress_reward=0.5)
    )
    for env in (plain, shaped):
        env.reset(np.arange(len(episodes)), episodes)
    rng = np.random.default_rng(0)
    difference = np.zeros(len(episodes))
    for _ in range(20):
        actions = rng.integers(0, DONE, len(episodes))  # movements only: every episode runs 20 steps
        difference += shaped.step(actions).reward - plain.step(actions).reward
    np.testing.assert_array_equal(shaped.pose, plain.pose)
    expected = 0.5 * (distances[starts] - distances[shaped.pose])
    np.testing.assert_allclose(difference, expected, atol=1e-5)
    assert np.abs(expected).max() > 0


@pytest.mark.slow
def test_feature_maps_are_gathered_into_one_array_only_when_read(library):
    scenes = [SCENE, "FloorPlan26"]
    env = BatchedNavEnv(library, scenes, 2)
    other = library["FloorPlan26"]
    env.reset(np.arange(2), [far_episode(library)[0], Episode("FloorPlan26", "Toaster", other.pose_tuple(5))])
    env.observe(("context", "target_embedding", "target_index"))
    assert "features" not in vars(env)  # a model that never reads them costs no copy
    features = env.observe(("features",))["features"]
    for slot, scene in enumerate(scenes):
        data, pose = library[scene], env.pose[slot] - env.scene_offset[scene]
        np.testing.assert_array_equal(
            features[slot], data.features[pose].astype(np.float32) * data.feature_scale
        )
