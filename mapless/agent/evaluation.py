"""The agents the evaluator drives: a trained model, with SAVN's test-time adaptation for adaptive
models, and the shortest-path oracle. Each returns action probabilities for every slot of a
:class:`~mapless.sim.vector.BatchedNavEnv`; the evaluator samples from them with each episode's own
uniforms (:func:`mapless.evaluate.runner.run_episodes`)."""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch

from mapless.actions import DONE, N_MOVEMENT_ACTIONS, NUM_ACTIONS
from mapless.agent.acting import AdaptingActor, PolicyMemory, observation_keys
from mapless.agent.precision import keep_compiled_kernels
from mapless.agent.rollout_lstm import RolloutLstm
from mapless.models.base import RecurrentNavModel
from mapless.models.memo import InViewMemo
from mapless.sim.vector import BatchedNavEnv, BatchStep


class Agent(Protocol):
    """What the runner drives. ``policy`` returns action probabilities ``[B, 6]`` for every slot."""

    observation_keys: tuple[str, ...]
    #: New episodes may start only when the global step count is a multiple of this (1: any step).
    start_every: int

    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None: ...

    def policy(self, obs: dict[str, np.ndarray], env: BatchedNavEnv) -> np.ndarray: ...

    def after_step(self, actions: np.ndarray, step: BatchStep) -> None: ...


class ModelAgent:
    """A recurrent :class:`~mapless.models.NavModel` without test-time adaptation."""

    start_every = 1

    def __init__(self, model, batch_size: int, bf16: bool = False):
        """``bf16``: step at training's ``a3c.precision: bf16`` (:meth:`RecurrentNavModel.rollout_step`)."""
        self.batch_size = batch_size
        self.model = model.eval()
        # The parameters are fixed for the whole evaluation: one bfloat16 copy of the LSTM matrices.
        self.lstm = None
        if bf16 and isinstance(model, RecurrentNavModel):
            keep_compiled_kernels()
            self.lstm = RolloutLstm(model.recurrent_cell, record=False, dtype=torch.bfloat16)
        # Gathering the feature map is the costly part of a step; skip it for models that ignore it.
        self.observation_keys = observation_keys(model)
        self.memory = PolicyMemory(model, batch_size)
        # The parameters are fixed for the whole evaluation, so the object GCNs' results are reused
        # across steps and episodes (mapless.models.memo).
        self.memo = InViewMemo()

    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None:
        self.memory.reset(torch.as_tensor(slots, dtype=torch.long))

    def _tensors(self, obs: dict[str, np.ndarray]) -> dict:
        return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in obs.items()}

    def policy(self, obs: dict[str, np.ndarray], env: BatchedNavEnv) -> np.ndarray:
        memory = self.memory
        with torch.inference_mode(), self.model.memoizing_in_view(self.memo):
            tensors = self._tensors(obs)
            if self.lstm is None:
                out = self.model(tensors, memory.hidden, memory.prev_policy)
            else:
                out = self.model.rollout_step(tensors, memory.hidden, memory.prev_policy, self.lstm)
            return memory.advance(out).numpy()

    def after_step(self, actions: np.ndarray, step: BatchStep) -> None:
        pass


class AdaptiveModelAgent(ModelAgent):
    """An adaptive model (learned interaction loss) with SAVN's test-time inner loop, φ frozen.

    Every slot owns fast weights (θ, reset to the trained θ when an episode starts): the small ones as
    per-slot copies, the LSTM matrices as θ plus the slot's low-rank inner-step factors, exactly as
    in training (:class:`mapless.agent.meta.TestTimeAdaptation`). Episodes start at
    k-step boundaries, so every slot's k-row buffer covers exactly its last k steps, computed with its
    current fast weights, and one batched ``TestTimeAdaptation.adapt`` serves all slots due for a step.
    """

    def __init__(self, model, batch_size: int):
        super().__init__(model, batch_size)
        self.adapter = AdaptingActor(model, batch_size)  # θ and φ fixed for the whole evaluation
        self.k = self.adapter.steps
        self.start_every = self.k
        self.alive = torch.zeros(batch_size, dtype=torch.bool)
        self.output = None  # the last step's ModelOutput, for the inner loop's k-row buffer

    @property
    def updates(self) -> np.ndarray:
        """Inner steps taken by each slot's current episode."""
        return self.adapter.updates

    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None:
        index = torch.as_tensor(slots, dtype=torch.long)
        self.adapter.reset_slots(index)
        self.memory.reset(index)
        self.alive[index] = True

    def policy(self, obs: dict[str, np.ndarray], env: BatchedNavEnv) -> np.ndarray:
        memory = self.memory
        # The graph must reach the current fast weights; only k steps of it are ever kept (SAVN: the
        # next step's input policy is not detached, so the inner gradient flows through it too).
        with self.model.memoizing_in_view(self.memo):
            self.output = self.adapter.forward(self._tensors(obs), memory.hidden, memory.prev_policy)
        return memory.advance(self.output).detach().numpy()

    def after_step(self, actions: np.ndarray, step: BatchStep) -> None:
        self.alive &= ~torch.from_numpy(step.terminated | step.truncated)
        self.adapter.observe(self.output, self.alive)


class OracleAgent:
    """Follows a shortest path to the target and calls ``Done`` on arrival (SR = SPL = 1 by
    construction): an upper bound and an end-to-end check of the metrics."""

    observation_keys: tuple[str, ...] = ()
    start_every = 1

    def __init__(self, batch_size: int):
        self.batch_size = batch_size
        self.distances: list[np.ndarray | None] = [None] * batch_size

    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None:
        for slot in slots:
            episode = env.episodes[slot]
            data = env.library[episode.scene]
            if episode.target_ids:
                goal = data.goal_mask_for_instances(data.goal_instances(episode.target, episode.target_ids))
                self.distances[slot] = data.distances_to(goal)
            else:
                self.distances[slot] = data.target_distances(episode.target)

    def policy(self, obs: dict[str, np.ndarray], env: BatchedNavEnv) -> np.ndarray:
        probs = np.zeros((env.batch_size, NUM_ACTIONS), dtype=np.float32)
        for slot in range(env.batch_size):
            dist = self.distances[slot]
            episode = env.episodes[slot]
            if dist is None or episode is None:
                probs[slot, DONE] = 1.0
                continue
            data = env.library[episode.scene]
            pose = int(env.pose[slot] - env.scene_offset[episode.scene])
            action = DONE
            if dist[pose] > 0:
                nexts = data.successors[pose, :N_MOVEMENT_ACTIONS]
                action = int(np.flatnonzero(dist[nexts] == dist[pose] - 1)[0])
            probs[slot, action] = 1.0
        return probs

    def after_step(self, actions: np.ndarray, step: BatchStep) -> None:
        pass
