"""The one episode loop: refill, k-step start boundaries, stopping, and the live-only batch."""

from __future__ import annotations

import numpy as np
from eval_fixtures import SCENES, fixture_episodes, fixture_library

from mapless.actions import DONE, MOVE_AHEAD, ROTATE_LEFT
from mapless.agent.episode_loop import EpisodeLoop
from mapless.sim.vector import BatchedNavEnv


class ScriptedAgent:
    """Calls Done in the slots of ``stoppers`` and turns left elsewhere; records what it was given."""

    observation_keys = ("target_index",)

    def __init__(self, stoppers: set[int] | None = None):
        self.stoppers = stoppers
        self.started: list[list[int]] = []
        self.acted_for: list[list[int]] = []
        self.obs_rows: list[int] = []
        self.ended: list[list[int]] = []

    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None:
        self.started.append(slots.tolist())

    def act(self, obs: dict[str, np.ndarray], slots: np.ndarray, env: BatchedNavEnv) -> np.ndarray:
        self.acted_for.append(slots.tolist())
        self.obs_rows.append(len(obs["target_index"]))
        if self.stoppers is None:
            return np.full(len(slots), DONE)
        return np.array([DONE if s in self.stoppers else ROTATE_LEFT for s in slots])

    def after_step(self, slots: np.ndarray, actions: np.ndarray, step, env: BatchedNavEnv) -> None:
        self.ended.append(np.flatnonzero(step.terminated | step.truncated).tolist())


def _env(batch: int, max_steps: int | None = None) -> BatchedNavEnv:
    return BatchedNavEnv(fixture_library(), sorted(SCENES), batch, mode="eval", max_steps=max_steps)


def _feed(episodes):
    queue = list(episodes)

    def feed(free: np.ndarray):
        taken = queue[: len(free)]
        del queue[: len(free)]
        return taken

    return feed


def test_finished_slots_take_the_next_episodes_until_the_feed_runs_dry() -> None:
    agent = ScriptedAgent()  # every episode lasts one step (Done)
    loop = EpisodeLoop(_env(2), agent, _feed(fixture_episodes(3)[:5]))
    assert loop.run() == 3  # 2 + 2 + 1 episodes
    assert agent.started == [[0, 1], [0, 1], [0]]
    assert agent.ended == [[0, 1], [0, 1], [0]]
    assert agent.acted_for == [[0, 1]] * 3  # without live_only every slot is computed, idle or not
    assert loop.free.all()


def test_new_episodes_start_only_at_k_step_boundaries() -> None:
    agent = ScriptedAgent()
    loop = EpisodeLoop(_env(2), agent, _feed(fixture_episodes(3)[:5]), start_every=2)
    # ticks 1 and 3 find every slot idle between boundaries; they still tick (an adaptive agent's
    # k-step clock stays aligned); tick 4 starts the last episode, tick 5 finds the feed dry
    assert loop.run() == 5
    assert agent.started == [[0, 1], [0, 1], [0]]
    assert agent.ended == [[0, 1], [], [0, 1], [], [0]]


def test_live_only_steps_just_the_running_episodes_and_stops_when_all_ended() -> None:
    episodes = fixture_episodes(3)[:3]
    agent = ScriptedAgent(stoppers={1})  # slot 1 stops at once; the others turn until the limit
    loop = EpisodeLoop(_env(3, max_steps=4), agent, live_only=True)
    loop.start(np.arange(3), episodes)
    assert loop.run(max_ticks=10) == 4
    assert agent.acted_for == [[0, 1, 2], [0, 2], [0, 2], [0, 2]]
    assert agent.obs_rows == [3, 2, 2, 2]  # observations only of the slots acted for
    assert agent.ended == [[1], [], [], [0, 2]]  # Done, then the 4-step limit


def test_max_ticks_cuts_a_segment_and_the_next_run_continues_it() -> None:
    agent = ScriptedAgent(stoppers=set())  # never Done: only the step limit ends an episode
    env = _env(2, max_steps=3)
    loop = EpisodeLoop(env, agent, _feed(fixture_episodes(6)))
    assert loop.run(max_ticks=2) == 2
    assert env.steps.tolist() == [2, 2] and not loop.free.any()
    assert loop.run(max_ticks=2) == 2  # the episodes in flight continue, then new ones start
    assert agent.ended == [[], [], [0, 1], []]
    assert agent.started == [[0, 1], [0, 1]]
    assert env.steps.tolist() == [1, 1]


def test_a_move_reaches_the_environment_for_the_slot_that_chose_it() -> None:
    class Mover(ScriptedAgent):
        def act(self, obs, slots, env):
            return np.array([MOVE_AHEAD if s == 1 else ROTATE_LEFT for s in slots])

    env = _env(2, max_steps=5)
    loop = EpisodeLoop(env, Mover(), live_only=True)
    loop.start(np.arange(2), fixture_episodes(3)[:2])
    before = env.pose.copy()
    loop.tick()
    for slot, turn in ((0, -45), (1, 0)):  # slot 0 turned left, slot 1 moved ahead (same heading)
        data, offset = env.library[env.episodes[slot].scene], env.scene_offset[env.episodes[slot].scene]
        assert data.yaw[env.pose[slot] - offset] == (data.yaw[before[slot] - offset] + turn) % 360
