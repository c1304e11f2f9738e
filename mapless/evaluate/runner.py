"""Evaluate a policy on a fixed episode set: batched episodes, parallel spawn workers, seeded sampling.

How it runs:

* Episodes are grouped by scene and the scenes split over ``workers`` spawn processes (each loads
  only its scenes; ``torch.set_num_threads(1)`` in each). A worker steps ``batch_size`` episodes in
  lockstep in one :class:`BatchedNavEnv`; a slot whose episode ends takes the next episode.
* Determinism: episode ``i`` of the set draws its action-sampling uniforms from
  ``default_rng([seed, i])``, and the model always runs on a full batch of ``batch_size`` rows (rows
  of idle slots are computed and ignored), so an episode's trajectory does not depend on which
  worker ran it or on which episodes shared its batch. Actions are sampled from the policy as the
  SAVN/MJOLNIR evaluators do (``greedy=True`` takes the argmax instead).
* Models run in ``eval()`` mode (dropout off) under ``inference_mode``. Adaptive models (savn, gve,
  spatt, cvmeta) adapt at test time as in training: every k = 6 steps, at most 4 times, one SGD step
  of the non-``ll`` parameters on the learned interaction loss, with φ frozen, from the trained θ in
  every episode (:class:`mapless.agent.meta.InnerLoop` with ``meta_train=False``). Their inner steps
  are batched, so new episodes start only at k-step boundaries (a slot waits at most k - 1 steps).
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from mapless.evaluate.metrics import EpisodeResult
from mapless.offline import offline_library
from mapless.scenes.catalogue import room_type_of
from mapless.sim.cache import fingerprint
from mapless.sim.config import SimConfig
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary
from mapless.sim.scene_data import DONE, N_MOVEMENT_ACTIONS
from mapless.sim.task import TargetFields, max_steps_for
from mapless.sim.vector import BatchedNavEnv, BatchStep

OBSERVATION_KEYS = ("context", "features", "target_embedding", "target_index")
NUM_ACTIONS = 6


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
        import torch

        self.torch = torch
        self.batch_size = batch_size
        self.bf16 = bf16
        if bf16:
            from mapless.agent.precision import keep_compiled_kernels

            keep_compiled_kernels()
        self.model = model.eval()
        from mapless.agent.acting import observation_keys

        # Gathering the feature map is the costly part of a step; skip it for models that ignore it.
        self.observation_keys = observation_keys(model)
        self.hidden = model.initial_state(batch_size)
        self.prev_policy = torch.zeros(batch_size, NUM_ACTIONS)
        # The parameters are fixed for the whole evaluation, so the object GCNs' results are reused
        # across steps and episodes (mapless.models.memo).
        from mapless.models.memo import InViewMemo

        self.memo = InViewMemo()

    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None:
        index = self.torch.as_tensor(slots, dtype=self.torch.long)
        for tensor in (*self.hidden, self.prev_policy):
            tensor[index] = 0.0

    def _tensors(self, obs: dict[str, np.ndarray]) -> dict:
        return {k: self.torch.from_numpy(np.ascontiguousarray(v)) for k, v in obs.items()}

    def policy(self, obs: dict[str, np.ndarray], env: BatchedNavEnv) -> np.ndarray:
        torch = self.torch
        with torch.inference_mode(), self.model.memoizing_in_view(self.memo):
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.bf16):
                out = self.model(self._tensors(obs), self.hidden, self.prev_policy)
            probs = torch.softmax(out.logits.float(), dim=-1)
        # Clone out of inference mode so start() can write rows in place.
        self.hidden = (out.hidden[0].float().clone(), out.hidden[1].float().clone())
        self.prev_policy = probs.clone()
        return probs.numpy()

    def after_step(self, actions: np.ndarray, step: BatchStep) -> None:
        pass


class AdaptiveModelAgent(ModelAgent):
    """An adaptive model (learned interaction loss) with SAVN's test-time inner loop, φ frozen.

    Every slot owns fast weights (θ, reset to the trained θ when an episode starts): the small ones as
    per-slot copies, the LSTM matrices as θ plus the slot's low-rank inner-step factors, exactly as
    in training (:class:`mapless.agent.meta.InnerLoop` with ``meta_train=False``). Episodes start at
    k-step boundaries, so every slot's k-row buffer covers exactly its last k steps, computed with its
    current fast weights, and one batched ``InnerLoop.adapt`` serves all slots due for a step.
    """

    def __init__(self, model, batch_size: int):
        super().__init__(model, batch_size)
        from mapless.agent.meta import InnerLoop

        torch = self.torch
        self.loop = InnerLoop(model, meta_train=False)
        for p in model.parameters():
            p.requires_grad_(False)  # θ and φ stay fixed; only the per-episode fast copies adapt
        self.state = self.loop.start(batch_size)
        self.k = self.loop.steps
        self.start_every = self.k
        self.alive = torch.zeros(batch_size, dtype=torch.bool)
        self.output = None  # the last step's ModelOutput, for the inner loop's k-row buffer

    @property
    def updates(self) -> np.ndarray:
        """Inner steps taken by each slot's current episode."""
        return self.state.slot_updates.numpy()

    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None:
        torch = self.torch
        index = torch.as_tensor(slots, dtype=torch.long)
        self.loop.reset_slots(self.state, index)
        with torch.no_grad():
            for tensor in (*self.hidden, self.prev_policy):
                tensor[index] = 0.0
        self.alive[index] = True

    def policy(self, obs: dict[str, np.ndarray], env: BatchedNavEnv) -> np.ndarray:
        torch = self.torch
        # The graph must reach the current fast weights; only k steps of it are ever kept.
        with self.model.memoizing_in_view(self.memo):
            self.output = self.loop.forward(self.state, self._tensors(obs), self.hidden, self.prev_policy)
        probs = torch.softmax(self.output.logits, dim=-1)
        self.hidden = self.output.hidden
        self.prev_policy = probs
        return probs.detach().numpy()

    def after_step(self, actions: np.ndarray, step: BatchStep) -> None:
        self.alive &= ~self.torch.from_numpy(step.terminated | step.truncated)
        # Every k steps the slots still running, and under their update limit, take an inner step.
        self.loop.observe(self.state, self.output, self.alive)


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


# -- agent and library specifications (picklable, rebuilt inside each worker) ---------------------
@dataclass(frozen=True)
class AgentSpec:
    """How a worker builds its agent: ``oracle``; a registered model (``model`` = ModelConfig fields,
    weights from ``checkpoint`` or fresh with ``init_seed``); or ``factory`` = ``"module:function"``
    called as ``function(batch_size, bf16)``."""

    kind: str = "model"
    model: dict = field(default_factory=dict)
    checkpoint: str | None = None
    init_seed: int = 0
    factory: str | None = None

    @property
    def label(self) -> str:
        if self.kind == "model":
            return str(self.model.get("name", "model"))
        return self.kind if self.kind != "factory" else str(self.factory)

    def build(self, batch_size: int, bf16: bool = False) -> Agent:
        """The agent, stepping ``batch_size`` episodes at once (``bf16``: see :class:`EvalSettings`)."""
        if self.kind == "oracle":
            return OracleAgent(batch_size)
        if self.kind == "factory":
            return _import(self.factory)(batch_size, bf16)
        model = load_model(self)
        if model.adaptive:
            return AdaptiveModelAgent(model, batch_size)
        return ModelAgent(model, batch_size, bf16)


def load_model(spec: AgentSpec):
    """The model of a spec: from a training checkpoint when given, else freshly initialised."""
    import torch

    from mapless.config import from_dict
    from mapless.models import ModelConfig, build_model

    if spec.checkpoint is not None:
        from mapless.checkpoint import load_model as load_trained

        return load_trained(spec.checkpoint)[0]
    torch.manual_seed(spec.init_seed)
    return build_model(from_dict(ModelConfig, spec.model))


@dataclass(frozen=True)
class LibrarySpec:
    """Scene source of the workers: the built-in simulator with ``sim`` (cache in ``cache_dir``), a
    SAVN/MJOLNIR offline data root, or a ``"module:function"`` factory returning a
    :class:`SceneLibrary` (tests)."""

    sim: SimConfig = field(default_factory=SimConfig)
    cache_dir: str | None = None
    factory: str | None = None
    offline_dir: str | None = None

    @classmethod
    def for_env(cls, env: Any, offline_dir: str | Path | None = None) -> LibrarySpec:
        """The scenes a run was trained on, from its ``TrainConfig.env`` (``offline_dir`` replaces the
        run's offline root, if any)."""
        offline = offline_dir or env.offline_dir
        return cls(sim=env.sim, cache_dir=env.cache_dir, offline_dir=str(offline) if offline else None)

    @property
    def sim_fingerprint(self) -> str | None:
        """The built-in simulator's fingerprint (what episode files record), None for other sources."""
        if self.factory is not None or self.offline_dir is not None:
            return None
        return fingerprint(self.sim)

    def build(self) -> SceneLibrary:
        if self.factory is not None:
            return _import(self.factory)()
        if self.offline_dir is not None:
            return offline_library(self.offline_dir, self.sim.category_set)
        return SceneLibrary.builtin(self.sim, Path(self.cache_dir) if self.cache_dir else None)


def _import(path: str) -> Callable[..., Any]:
    import importlib

    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def target_fields(category_set: str) -> TargetFields:
    """Observation fields of the target: the category set's GloVe vector (docs/observations.md)."""
    return TargetFields(category_set)


# -- the episode loop -------------------------------------------------------------------------------
@dataclass(frozen=True)
class EvalSettings:
    """``batch_size`` episodes per worker in lockstep; ``workers`` spawn processes (1: in-process);
    ``seed`` of the action sampling; ``greedy`` argmax actions; ``bf16``: run non-adaptive models
    under bfloat16 autocast (2x faster GCNs on CPUs with AVX512-BF16 or AMX; the policies differ
    from float32 by rounding, so compare models under the same setting)."""

    batch_size: int = 32
    workers: int = 2
    seed: int = 0
    greedy: bool = False
    bf16: bool = False
    max_steps: int | None = None
    category_set: str = "mjolnir101"


def run_episodes(
    agent: Agent,
    library: SceneLibrary,
    episodes: Sequence[Episode],
    indices: Sequence[int],
    settings: EvalSettings,
) -> list[EpisodeResult]:
    """Run ``episodes`` (whose positions in the full set are ``indices``) to the end, in one process."""
    batch = getattr(agent, "batch_size", settings.batch_size)
    scenes = sorted({e.scene for e in episodes})
    env = BatchedNavEnv(
        library, scenes, batch, targets=target_fields(settings.category_set), mode="eval",
        max_steps=settings.max_steps,
    )  # fmt: skip
    horizon = settings.max_steps or max(max_steps_for(library[s].room_type, "eval") for s in scenes)
    queue = list(range(len(episodes)))
    queue.reverse()  # pop() from the end takes episodes in set order
    slot_item = np.full(batch, -1, dtype=np.int64)
    uniforms = np.zeros((batch, horizon + 1))
    poses = np.zeros((batch, horizon), dtype=np.int64)
    actions_log = np.zeros((batch, horizon), dtype=np.int8)
    failed = np.zeros(batch, dtype=np.int64)
    reward = np.zeros(batch)
    start_pose = np.zeros(batch, dtype=np.int64)
    offsets = np.zeros(batch, dtype=np.int64)
    results: list[EpisodeResult] = []
    tick = 0
    while True:
        free = np.flatnonzero(slot_item < 0)
        if len(free) and queue and tick % agent.start_every == 0:
            slots = free[: len(queue)]
            items = [queue.pop() for _ in slots]
            env.reset(slots, [episodes[i] for i in items])
            for slot, item in zip(slots, items, strict=True):
                slot_item[slot] = item
                uniforms[slot] = np.random.default_rng([settings.seed, int(indices[item])]).random(
                    horizon + 1
                )
                offsets[slot] = env.scene_offset[episodes[item].scene]
            start_pose[slots] = env.pose[slots] - offsets[slots]
            failed[slots] = 0
            reward[slots] = 0.0
            agent.start(slots, env)
        if not queue and not (slot_item >= 0).any():
            break
        # With every slot idle (an adaptive agent waiting for its next k-step boundary) the step
        # below is a no-op for the environment but keeps the agent's k-step clock aligned.
        obs = env.observe(agent.observation_keys) if agent.observation_keys else {}
        probs = agent.policy(obs, env)
        t = env.steps.copy()
        if settings.greedy:
            actions = probs.argmax(axis=1)
        else:
            cdf = np.cumsum(probs, axis=1, dtype=np.float64)
            u = uniforms[np.arange(batch), np.minimum(t, horizon)] * cdf[:, -1]
            actions = np.minimum((cdf <= u[:, None]).sum(axis=1), NUM_ACTIONS - 1)
        step = env.step(actions)
        agent.after_step(actions, step)
        tick += 1
        act = np.flatnonzero(step.active)
        poses[act, t[act]] = env.pose[act] - offsets[act]
        actions_log[act, t[act]] = actions[act]
        failed += step.failed_action
        reward += step.reward
        for slot in np.flatnonzero(step.active & (step.terminated | step.truncated)):
            item = int(slot_item[slot])
            episode = episodes[item]
            length = int(env.steps[slot])
            results.append(
                EpisodeResult(
                    index=int(indices[item]),
                    episode_id=episode.episode_id,
                    scene=episode.scene,
                    room_type=room_type_of(episode.scene),
                    target=episode.target,
                    success=bool(step.success[slot]),
                    length=length,
                    optimal_length=int(env.optimal_length[slot]),
                    called_done=bool(step.terminated[slot]),
                    failed_actions=int(failed[slot]),
                    reward=float(reward[slot]),
                    start_pose=int(start_pose[slot]),
                    poses=tuple(poses[slot, :length].tolist()),
                    actions=tuple(actions_log[slot, :length].tolist()),
                )
            )
            slot_item[slot] = -1
    return sorted(results, key=lambda r: r.index)


# -- parallel evaluation ----------------------------------------------------------------------------
@dataclass
class EvalRun:
    """Results of one evaluation plus how long it took."""

    results: list[EpisodeResult]
    seconds: float  # wall time, worker start-up (imports, scene loading, model building) included
    steps: int
    worker_rss_mb: list[float] = field(default_factory=list)
    #: Episode-loop time of the slowest worker (start-up excluded): the steady-state throughput.
    loop_seconds: float = float("nan")

    @property
    def steps_per_second(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else float("nan")

    @property
    def loop_steps_per_second(self) -> float:
        return self.steps / self.loop_seconds if self.loop_seconds > 0 else float("nan")


def partition(episodes: Sequence[Episode], workers: int) -> list[list[int]]:
    """Split episode indices over workers by whole scenes (a worker loads only its scenes), balancing
    the step budget (100 or 200 per episode); scenes go largest first to the least-loaded worker."""
    by_scene: dict[str, list[int]] = {}
    for i, e in enumerate(episodes):
        by_scene.setdefault(e.scene, []).append(i)
    cost = {s: len(ix) * max_steps_for(room_type_of(s), "eval") for s, ix in by_scene.items()}
    shares: list[list[int]] = [[] for _ in range(workers)]
    load = [0] * workers
    for scene in sorted(by_scene, key=lambda s: (-cost[s], s)):
        w = int(np.argmin(load))
        shares[w].extend(by_scene[scene])
        load[w] += cost[scene]
    return [sorted(s) for s in shares if s]


def _rss_mb() -> float:
    """Peak resident set size of this process (MB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _worker(
    job: tuple[AgentSpec, LibrarySpec, list[Episode], list[int], EvalSettings, int],
) -> tuple[list[dict], float, float]:
    agent_spec, library_spec, episodes, indices, settings, threads = job
    import torch

    if threads:
        torch.set_num_threads(threads)
    library = library_spec.build()
    for scene in sorted({e.scene for e in episodes}):
        library[scene]  # load (or build) before the clock starts
    agent = agent_spec.build(settings.batch_size, settings.bf16)
    start = time.perf_counter()
    results = run_episodes(agent, library, episodes, indices, settings)
    return [r.to_dict() for r in results], _rss_mb(), time.perf_counter() - start


def evaluate(
    agent: AgentSpec,
    episodes: Sequence[Episode],
    settings: EvalSettings | None = None,
    library: LibrarySpec | None = None,
    progress: Callable[[str], None] | None = None,
) -> EvalRun:
    """Evaluate ``agent`` on ``episodes`` with ``settings.workers`` spawn workers; results are in
    episode order and identical for any worker count."""
    settings = settings or EvalSettings()
    library = library or LibrarySpec()
    episodes = list(episodes)
    scenes = sorted({e.scene for e in episodes})
    library.build().prepare(scenes)  # a bar only when some scene has to be built
    workers = max(1, min(settings.workers, len(scenes)))
    shares = partition(episodes, workers)
    jobs = [(agent, library, [episodes[i] for i in share], share, settings, 1) for share in shares]
    start = time.perf_counter()
    if workers == 1:
        # In-process: the caller's torch thread setting stays as it is.
        out = [_worker((*jobs[0][:5], 0))]
    else:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
            out = list(pool.map(_worker, jobs))
    seconds = time.perf_counter() - start
    results = sorted((EpisodeResult.from_dict(d) for part, _, _ in out for d in part), key=lambda r: r.index)
    if progress:
        progress(f"{agent.label}: {len(results)} episodes in {seconds:.1f} s")
    steps = sum(r.length for r in results)
    return EvalRun(results, seconds, steps, [rss for _, rss, _ in out], max(t for _, _, t in out))
