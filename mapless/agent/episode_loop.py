"""The one episode loop: the slots of a :class:`~mapless.sim.vector.BatchedNavEnv` stepped in
lockstep by an agent.

Every way this project plays episodes runs through :class:`EpisodeLoop`:

* the A3C trainers' lockstep batches (:func:`mapless.train.rollout.run_batch`; the Hogwild worker is
  the same at B = 1), which step only the episodes still running (``live_only``);
* PPO's segments, where a finished slot takes a new episode at once, and its whole-episode batches
  for adaptive models (:class:`mapless.train.segments.SegmentCollector`);
* the evaluator (:func:`mapless.evaluate.runner.run_episodes`), whose slots take the next episodes of
  a fixed set, adaptive agents only at their k-step boundaries (``start_every``).

What differs between them is the :class:`LoopAgent` (how observations become actions, and what it
records) and the ``feed`` (where new episodes come from). Per tick:

1. refill: when there is a feed and the tick is a multiple of ``start_every``, the free slots take the
   episodes the feed gives (fewer than asked, or none, once it runs dry);
2. stop when no slot holds an episode and the feed has run dry (or there is none);
3. the agent acts for ``slots``: the slots holding a running episode with ``live_only``, else all
   ``B`` (rows of idle slots are computed and ignored, so the model always sees a full batch);
4. the environment steps; slots whose episode ended become free; the agent sees the step.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from mapless.sim.episode import Episode
from mapless.sim.vector import BatchedNavEnv, BatchStep

#: Given the free slots, the episodes to start in the first of them (fewer, or none, when dry).
Feed = Callable[[np.ndarray], Sequence[Episode]]


class LoopAgent(Protocol):
    """What the loop drives."""

    #: observation keys the agent reads (``()``: none are gathered)
    observation_keys: tuple[str, ...]

    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None:
        """New episodes begin in ``slots`` (the environment is already reset there)."""

    def act(self, obs: dict[str, np.ndarray], slots: np.ndarray, env: BatchedNavEnv) -> np.ndarray:
        """Actions ``[len(slots)]`` of ``slots``, whose observations ``obs`` holds (in that order)."""

    def after_step(self, slots: np.ndarray, actions: np.ndarray, step: BatchStep, env: BatchedNavEnv) -> None:
        """The environment took ``actions`` (all ``B`` slots; ``slots`` are those the agent acted for)."""


class EpisodeLoop:
    """Steps ``env`` with ``agent``; see the module docstring for the tick."""

    def __init__(
        self,
        env: BatchedNavEnv,
        agent: LoopAgent,
        feed: Feed | None = None,
        *,
        start_every: int = 1,
        live_only: bool = False,
    ):
        self.env, self.agent, self.feed = env, agent, feed
        self.start_every = start_every
        self.live_only = live_only
        #: slots without an episode in flight (the environment's ``done`` is True there too)
        self.free = np.ones(env.batch_size, dtype=bool)
        self.ticks = 0
        self._dry = feed is None

    def start(self, slots: np.ndarray, episodes: Sequence[Episode]) -> None:
        """Start ``episodes`` in ``slots`` now (the loop's own refill does the same)."""
        slots = np.asarray(slots, dtype=np.int64)
        self.env.reset(slots, list(episodes))
        self.free[slots] = False
        self.agent.start(slots, self.env)

    def tick(self) -> bool:
        """One lockstep step of every slot; False (and no step) when there is nothing left to play."""
        if self.feed is not None and self.ticks % self.start_every == 0 and self.free.any():
            free = np.flatnonzero(self.free)
            episodes = self.feed(free)
            self._dry = len(episodes) < len(free)
            if len(episodes):
                self.start(free[: len(episodes)], episodes)
        if self.free.all() and self._dry:
            return False
        env = self.env
        slots = np.flatnonzero(~self.free) if self.live_only else np.arange(env.batch_size)
        keys = self.agent.observation_keys
        obs = env.observe(keys) if keys else {}
        if self.live_only and len(slots) < env.batch_size:
            obs = {key: value[slots] for key, value in obs.items()}
        actions = np.zeros(env.batch_size, dtype=np.int64)
        actions[slots] = self.agent.act(obs, slots, env)
        step = env.step(actions)
        self.free |= step.terminated | step.truncated
        self.ticks += 1
        self.agent.after_step(slots, actions, step, env)
        return True

    def run(self, max_ticks: int | None = None) -> int:
        """Tick until nothing is left to play or ``max_ticks`` ticks were taken; returns the ticks."""
        taken = 0
        while (max_ticks is None or taken < max_ticks) and self.tick():
            taken += 1
        return taken
