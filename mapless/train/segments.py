"""Collecting PPO experience from the batched environment.

Two layouts, one :class:`Segment` type:

* **segments** (non-adaptive models): ``N`` environment slots step for ``T`` steps; a slot whose
  episode ends takes a new one at once (no slot idles), the recurrent state is zeroed at episode
  starts and carried across segments, and time-limit truncations are bootstrapped with the value of
  the state the episode was cut in.
* **whole episodes** (adaptive models, and the others with ``ppo.whole_episodes``): ``N``
  episodes start together and run to their end (``T`` = the training step limit); a slot whose
  episode ended idles, masked out. Adaptive models act with SAVN's inner loop at its test-time
  setting: every ``k`` steps one SGD step of the episode's own fast weights on the learned
  interaction loss. An episode's adaptation state cannot be carried across a segment boundary into
  a replay, so each replay starts at the episode's first step (docs/guide/training.md, "PPO"). As in the
  references, the 30-step limit is not bootstrapped there, unless ``bootstrap_time_limit``: then,
  as for segments, with V of the state the episode was cut in (under the episode's adapted fast
  weights).

Actions are drawn by inverse CDF from uniforms of the trainer's numpy generator, so a run is
reproducible from its seed and its checkpoint.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from mapless.agent.acting import AdaptingActor, PolicyMemory, policy_probabilities, sample_actions, to_tensors
from mapless.agent.episode_loop import EpisodeLoop
from mapless.episodes.sampler import TrainingSampler
from mapless.evaluate.metrics import spl
from mapless.models.base import ModelOutput, NavModel
from mapless.models.memo import InViewMemo
from mapless.sim.episode import Episode
from mapless.sim.vector import BatchedNavEnv, BatchStep


@dataclass
class Segment:
    """``T`` steps of ``N`` slots (``[T, N, ...]``), everything a PPO update needs."""

    obs: dict[str, Tensor]
    prev_policy: Tensor  # [T, N, 6] the previous policy each step was given
    starts: Tensor  # [T, N] bool: the step opened an episode
    actions: Tensor
    log_prob: Tensor
    values: Tensor
    rewards: Tensor
    terminated: Tensor  # [T, N] bool
    truncated: Tensor  # [T, N] bool
    bootstrap: Tensor  # [T, N] V(s_{t+1}) of truncated steps, 0 elsewhere
    mask: Tensor  # [T, N] 1 where the slot took a step (whole episodes: 0 after the end)
    expert: Tensor  # [T, N] the shortest-path expert's action, -1 where none (or not recorded)
    hidden: tuple[Tensor, Tensor]  # [N, H] before the first step
    next_value: Tensor  # [N] V after the last step (0 where the episode ended)
    finished: dict[str, np.ndarray]  # success, spl, length, reward of the episodes that ended

    @property
    def frames(self) -> int:
        return int(self.mask.sum())


_RECORDED = (
    "obs",
    "prev_policy",
    "starts",
    "actions",
    "log_prob",
    "values",
    "rewards",
    "terminated",
    "truncated",
    "bootstrap",
    "mask",
    "expert",
)


def _finished_rows(rows: list[tuple[bool, float, int, float]]) -> dict[str, np.ndarray]:
    array = np.array(rows, dtype=np.float64).reshape(-1, 4)
    return {key: array[:, i] for i, key in enumerate(("success", "spl", "length", "reward"))}


class _Acted(NamedTuple):
    """What :meth:`SegmentCollector.act` decided, for :meth:`SegmentCollector.after_step` to record."""

    obs: dict[str, Tensor]
    active_before: np.ndarray  # [N] the slot's episode was running before the step
    output: ModelOutput
    action: Tensor
    expert: np.ndarray


class SegmentCollector:
    """Steps ``env`` (``N`` slots) with a model, refilling finished slots from ``sampler``.

    It is the :class:`~mapless.agent.episode_loop.LoopAgent` of its own
    :class:`~mapless.agent.episode_loop.EpisodeLoop`, which persists across segments (a slot's
    episode in flight continues in the next segment)."""

    def __init__(
        self,
        model: NavModel,
        env: BatchedNavEnv,
        sampler: TrainingSampler,
        obs_keys: tuple[str, ...],
        device: torch.device,
        whole_episodes: bool,
        adapting: bool = False,
        expert: bool = False,
        bootstrap_time_limit: bool = False,
    ):
        """``adapting``: act through the inner loop (adaptive models; needs ``whole_episodes``).
        ``expert``: record the shortest-path expert's action at every step (imitation).
        ``bootstrap_time_limit``: whole episodes cut by the step limit are bootstrapped (segments
        always are)."""
        if adapting and not whole_episodes:
            raise ValueError("an adapting collector plays whole episodes (its fast weights start at θ)")
        self.model, self.env, self.sampler = model, env, sampler
        self.observation_keys, self.device = obs_keys, device
        self.whole_episodes, self.adapting = whole_episodes, adapting
        # The references' R = 0 at the step limit: a truncation of a whole episode is an end.
        self.cut_is_end = np.bool_(whole_episodes and not bootstrap_time_limit)
        self.expert = expert
        n = env.batch_size
        self.memory = PolicyMemory(model, n, device)
        self.reward_sum = np.zeros(n)
        self.loop = EpisodeLoop(env, self, feed=self._feed)
        # per collect(): the generator, the acting state and what is recorded
        self._rng: np.random.Generator | None = None
        self._opening = False
        self._starts = np.zeros(n, dtype=bool)
        self._actor: AdaptingActor | None = None
        self._memo: InViewMemo | None = None
        self._record: dict[str, list] = {}
        self._finished: list[tuple[bool, float, int, float]] = []
        self._acted: _Acted | None = None  # the current step, between act() and after_step()

    # -- resumable state ---------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The slots' episodes in flight (plain data and tensors, for a weights-only checkpoint)."""
        env = self.env
        return {
            "episodes": [e.to_dict() if e is not None else None for e in env.episodes],
            "pose": torch.as_tensor(env.pose),
            "steps": torch.as_tensor(env.steps),
            "done": torch.as_tensor(env.done),
            "seen_parents": torch.as_tensor(env.seen_parents),
            "hidden": [t.detach().cpu() for t in self.memory.hidden],
            "prev_policy": self.memory.prev_policy.cpu(),
            "reward_sum": torch.as_tensor(self.reward_sum),
            "needs_episode": torch.as_tensor(self.loop.free),
        }

    def load_state_dict(self, state: dict) -> None:
        env = self.env
        for slot, episode in enumerate(state["episodes"]):
            if episode is not None:
                env.reset([slot], [Episode.from_dict(episode)])
        env.pose[:] = state["pose"].numpy()
        env.steps[:] = state["steps"].numpy()
        env.done[:] = state["done"].numpy()
        env.seen_parents[:] = state["seen_parents"].numpy()
        self.memory.hidden = tuple(t.to(self.device) for t in state["hidden"])
        self.memory.prev_policy = state["prev_policy"].to(self.device)
        self.reward_sum = state["reward_sum"].numpy().copy()
        self.loop.free[:] = state["needs_episode"].numpy()

    # -- collection ------------------------------------------------------------------------------
    def collect(self, steps: int, rng: np.random.Generator) -> Segment:
        """Act for ``steps`` steps (whole episodes: until every episode ended, at most ``steps``)."""
        n = self.env.batch_size
        if self.whole_episodes:
            self.loop.free[:] = True
            self._opening = True
        if self.adapting:
            self._actor = AdaptingActor(self.model, n)
        self._rng, self._memo = rng, InViewMemo(max_rows=None)
        h0 = tuple(t.detach().clone() for t in self.memory.hidden)
        self._record = {k: [] for k in _RECORDED}
        self._finished = []
        try:
            self.loop.run(max_ticks=steps)
        finally:
            if self._actor is not None:
                self._actor.close()
                self._actor = None
        record = self._record
        stacked = {
            "obs": {k: torch.stack([o[k] for o in record["obs"]]) for k in record["obs"][0]},
            **{k: torch.stack(v) for k, v in record.items() if k != "obs"},
        }
        finished = _finished_rows(self._finished)
        return Segment(**stacked, hidden=h0, next_value=self._next_value(), finished=finished)

    def _feed(self, free: np.ndarray) -> list[Episode]:
        """New episodes for the free slots: at every step for segments, once for whole episodes."""
        if self.whole_episodes and not self._opening:
            return []
        self._opening = False
        return [self.sampler.sample(self._rng) for _ in free]

    def _next_value(self) -> Tensor:
        """V after the segment's last step (whole episodes: 0, every episode has ended)."""
        n = self.env.batch_size
        if self.whole_episodes:
            return torch.zeros(n, device=self.device)
        obs = to_tensors(self.env.observe(self.observation_keys), self.device)
        with self.model.memoizing_in_view(self._memo):
            return self.model.predict_values(obs, self.memory.hidden, self.memory.prev_policy)

    # -- the loop's agent ----------------------------------------------------------------------------
    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None:
        self.memory.reset(torch.as_tensor(slots, device=self.device))
        self.reward_sum[slots] = 0.0
        self._starts[slots] = True

    def act(self, obs: dict[str, np.ndarray], slots: np.ndarray, env: BatchedNavEnv) -> np.ndarray:
        n, device = env.batch_size, self.device
        tensors, memory = to_tensors(obs, device), self.memory
        with self.model.memoizing_in_view(self._memo):
            if self._actor is not None:
                out = self._actor.forward(tensors, memory.hidden, memory.prev_policy)
            else:
                with torch.no_grad():
                    out = self.model(tensors, memory.hidden, memory.prev_policy)
        action = sample_actions(policy_probabilities(out.logits), self._rng.random(n))
        expert = env.expert_actions() if self.expert else np.full(n, -1)
        self._acted = _Acted(tensors, ~env.done, out, torch.as_tensor(action, device=device), expert)
        return action

    def after_step(self, slots: np.ndarray, actions: np.ndarray, step: BatchStep, env: BatchedNavEnv) -> None:
        n, device, acted = env.batch_size, self.device, self._acted
        out = acted.output
        logits = out.logits.detach()
        cut_is_end = self.cut_is_end
        bootstrap = torch.zeros(n, device=device)
        prev_policy = self.memory.prev_policy  # the one this step was given
        # The inner loop's test-time steps differentiate through the recurrence back to the start
        # of their chunk (it cuts the graph there itself), as the replay does; the policy given to
        # the next step is a constant, as in the replay, which reads it from the record.
        hidden = out.hidden if self._actor is not None else tuple(t.detach() for t in out.hidden)
        self.memory.advance(ModelOutput(logits, out.value, hidden))
        if self._actor is not None:
            self._actor.observe(out, torch.as_tensor(~env.done, device=device))
        if step.truncated.any() and not cut_is_end:
            bootstrap[torch.as_tensor(step.truncated, device=device)] = self._values_after(step.truncated)
        self.reward_sum += step.reward
        for slot in np.flatnonzero(step.terminated | step.truncated):
            length, success = int(env.steps[slot]), bool(step.success[slot])
            optimal = int(env.optimal_length[slot])
            self._finished.append((success, spl(success, length, optimal), length, self.reward_sum[slot]))
        action = acted.action
        for key, value in (
            ("obs", acted.obs),
            ("prev_policy", prev_policy),
            ("starts", torch.as_tensor(self._starts, device=device)),
            ("actions", action),
            ("log_prob", F.log_softmax(logits, -1).gather(-1, action.unsqueeze(-1)).squeeze(-1)),
            ("values", out.value.detach().reshape(n)),
            ("rewards", torch.as_tensor(step.reward, device=device)),
            ("terminated", torch.as_tensor(step.terminated | (step.truncated & cut_is_end), device=device)),
            ("truncated", torch.as_tensor(step.truncated & ~cut_is_end, device=device)),
            ("bootstrap", bootstrap),
            ("mask", torch.as_tensor(acted.active_before, dtype=torch.float32, device=device)),
            ("expert", torch.as_tensor(acted.expert, device=device)),
        ):
            self._record[key].append(value)
        self._starts = np.zeros(n, dtype=bool)

    def _values_after(self, slots: np.ndarray) -> Tensor:
        """V of the states the truncated episodes in ``slots`` were cut in."""
        index = torch.as_tensor(np.flatnonzero(slots), device=self.device)
        obs_all = to_tensors(self.env.observe(self.observation_keys), self.device)
        memory = self.memory
        with self.model.memoizing_in_view(self._memo):
            if self._actor is not None:  # the adapted fast weights hold one row per slot
                return self._actor.value(obs_all, memory.hidden, memory.prev_policy).index_select(0, index)
            obs = {k: v.index_select(0, index) for k, v in obs_all.items()}
            rows = tuple(t.index_select(0, index) for t in memory.hidden)
            return self.model.predict_values(obs, rows, memory.prev_policy.index_select(0, index))
