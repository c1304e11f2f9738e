"""Gymnasium environment: one ObjectNav episode at a time in a precomputed scene.

Registered as ``mapless/ObjectNav-v0``. Observation space: a ``Dict`` of one ``Box`` per key of
:data:`mapless.observations.OBSERVATION` (docs/guide/simulator.md, "Observations"); a key a row
holds one number of (``target_index``) is a one-element box, not a 0-d array, because
stable-baselines3's policies refuse 0-d observations.

Actions: Discrete(6) = MoveAhead, RotateLeft, RotateRight, LookUp, LookDown, Done. The episode
terminates on ``Done`` (success iff a target instance is visible) and is truncated at the step
limit. ``info`` carries ``success``, ``optimal_length``, ``visited`` (a tuple of the pose ids so
far), ``failed_action``, ``pose`` (pose id; ``env.data.key(pose)`` gives the SAVN pose key) and
``mapless_episode`` (the :class:`Episode` being played). The names keep off ``info["episode"]``,
which gymnasium's ``RecordEpisodeStatistics`` and stable-baselines3's ``Monitor`` write their
episode statistics into, and every value is immutable, so that a stored ``info`` never changes.

``render_mode="rgb_array"``: :meth:`NavEnv.render` returns a top-down frame of the room, the agent,
its path and the target instances (:class:`~mapless.sim.pictures.TopDownFrame`).

The task rules live in one place, :class:`~mapless.sim.vector.BatchedNavEnv`: this class is a thin
adapter that plays slot 0 of a batched environment of size 1 over the current episode's scene, and
adds only what gymnasium asks for (episode selection, the spaces, per-step tuples).
"""

from __future__ import annotations

from typing import ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from mapless.actions import ACTIONS
from mapless.errors import MaplessError
from mapless.observations import OBSERVATION_KEYS, ObservationSizes, gym_space
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary
from mapless.sim.pictures import TopDownFrame
from mapless.sim.scene_data import SceneData
from mapless.sim.task import RewardConfig, TargetFields, resolve_target_fields
from mapless.sim.vector import BatchedNavEnv


class NavEnv(gym.Env):
    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(
        self,
        library: SceneLibrary,
        episodes: list[Episode] | None = None,
        sampler=None,
        targets: TargetFields | None = None,
        rewards: RewardConfig | None = None,
        mode: str = "train",
        max_steps: int | None = None,
        category_set: str | None = None,
        render_mode: str | None = None,
        render_size: int = 256,
    ):
        if episodes is None and sampler is None:
            raise MaplessError("NavEnv needs a list of episodes or an episode sampler")
        if episodes is not None and len(episodes) == 0:  # reset would pick from nothing
            raise MaplessError(
                "NavEnv got an empty list of episodes; give at least one, or an episode sampler"
            )
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise MaplessError(
                f"render_mode {render_mode!r} is not one of {', '.join(self.metadata['render_modes'])}"
            )
        self.render_mode = render_mode
        self.render_size = render_size
        self._frames: dict[str, TopDownFrame] = {}
        self.library = library
        self.episodes = episodes
        self.sampler = sampler
        self.targets = resolve_target_fields(targets, category_set)
        self.rewards = rewards or RewardConfig()
        self.mode = mode
        self.fixed_max_steps = max_steps
        n_cat = len(self.targets.categories)
        self.action_space = spaces.Discrete(len(ACTIONS))
        self.observation_space = gym_space(ObservationSizes(n_cat))
        self._next_fixed = 0
        #: the batched environment of the current episode's scene (rebuilt when the scene changes)
        self.batched: BatchedNavEnv | None = None
        self.visited: tuple[int, ...] = ()

    # -- the current episode, read from the batched environment's slot 0 ------------------------
    @property
    def episode(self) -> Episode:
        return self.batched.episodes[0]

    @property
    def data(self) -> SceneData:
        return self.library[self.episode.scene]

    @property
    def pose(self) -> int:
        """The pose id within the episode's scene."""
        return int(self.batched.pose[0] - self.batched.scene_offset[self.episode.scene])

    @property
    def steps(self) -> int:
        return int(self.batched.steps[0])

    @property
    def max_steps(self) -> int:
        return int(self.batched.max_steps[0])

    @property
    def optimal_length(self) -> int:
        return int(self.batched.optimal_length[0])

    # -- gymnasium API ---------------------------------------------------------------------------
    def _select_episode(self, options: dict | None) -> Episode:
        if options and "episode" in options:
            return options["episode"]
        if self.episodes is not None:
            episode = self.episodes[self._next_fixed % len(self.episodes)]
            self._next_fixed += 1
            return episode
        return self.sampler.sample(self.np_random)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            # A seed starts the episode stream over, as gymnasium promises: the fixed list from its
            # first episode, the sampler from the start of its room cycle.
            self._next_fixed = 0
            if self.sampler is not None:
                self.sampler.position = 0
        episode = self._select_episode(options)
        if self.batched is None or episode.scene not in self.batched.scene_offset:
            self.batched = BatchedNavEnv(
                self.library,
                [episode.scene],
                1,
                targets=self.targets,
                rewards=self.rewards,
                mode=self.mode,
                max_steps=self.fixed_max_steps,
            )
        self.batched.reset([0], [episode])
        self.visited = (self.pose,)
        return self._observation(), self._info(success=False, failed=False)

    def step(self, action: int):
        result = self.batched.step(np.array([int(action)]))
        terminated = bool(result.terminated[0])
        if not terminated:
            self.visited = (*self.visited, self.pose)
        info = self._info(success=bool(result.success[0]), failed=bool(result.failed_action[0]))
        return self._observation(), float(result.reward[0]), terminated, bool(result.truncated[0]), info

    def render(self) -> np.ndarray | None:
        """The current step seen from above (``render_mode="rgb_array"``), ``[H, W, 3]`` uint8."""
        if self.render_mode is None:
            gym.logger.warn(
                'NavEnv.render() without a render_mode: make the env with render_mode="rgb_array"'
            )
            return None
        scene = self.episode.scene
        if scene not in self._frames:
            self._frames[scene] = TopDownFrame(self.data, self.render_size)
        goal = self.data.goal_instances(self.episode.target, self.episode.target_ids)
        return self._frames[scene].draw(self.pose, goal, self.visited)

    def _observation(self) -> dict:
        observed = self.batched.observe(OBSERVATION_KEYS).items()
        return {key: value[0].reshape(self.observation_space[key].shape) for key, value in observed}

    def _info(self, success: bool, failed: bool) -> dict:
        return {
            "success": success,
            "optimal_length": self.optimal_length,
            "visited": self.visited,
            "failed_action": failed,
            "pose": self.pose,
            "mapless_episode": self.episode,
        }
