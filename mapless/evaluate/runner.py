"""Evaluate a policy on a fixed episode set: batched episodes, parallel spawn workers, seeded sampling.

How it runs:

* The agents (a model, an adaptive model, the oracle) are :mod:`mapless.agent.evaluation`'s; the
  episodes run through the one episode loop (:class:`~mapless.agent.episode_loop.EpisodeLoop`).
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
  of the parameters the model's roles adapt on the learned interaction loss, with φ frozen, from the trained θ in
  every episode (:class:`mapless.agent.meta.TestTimeAdaptation`). Their inner steps
  are batched, so new episodes start only at k-step boundaries (a slot waits at most k - 1 steps).
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mapless.agent.acting import sample_actions
from mapless.agent.episode_loop import EpisodeLoop
from mapless.agent.evaluation import AdaptiveModelAgent, Agent, ModelAgent, OracleAgent
from mapless.errors import MaplessError
from mapless.evaluate.metrics import EpisodeResult, sightings
from mapless.offline import offline_library
from mapless.processes import exit_with_parent
from mapless.scenes.catalogue import room_type_of
from mapless.sim.cache import fingerprint
from mapless.sim.config import SimConfig
from mapless.sim.episode import Episode
from mapless.sim.library import SceneLibrary
from mapless.sim.task import TargetFields, max_steps_for
from mapless.sim.vector import BatchedNavEnv, BatchStep

if TYPE_CHECKING:
    from mapless.episodes.protocols import Protocol
    from mapless.models import NavModel


# -- agent and library specifications (picklable, rebuilt inside each worker) ---------------------
@dataclass(frozen=True)
class AgentSpec:
    """How a worker builds its agent: ``oracle``; a registered model (``model`` = ModelConfig fields,
    weights from ``checkpoint`` or fresh with ``init_seed``); or ``factory`` = ``"module:function"``
    called as ``function(batch_size, bf16)``. ``adapt``: an adaptive model's test-time adaptation;
    False runs its trained θ_0 as a plain recurrent policy (the cvmeta ablation's row a).
    ``inner_lr``: an adaptive model's test-time inner learning rate instead of its trained one (how
    far adaptation moves the policy; docs/results/learning.md)."""

    kind: str = "model"
    model: dict = field(default_factory=dict)
    checkpoint: str | None = None
    init_seed: int = 0
    factory: str | None = None
    adapt: bool = True
    inner_lr: float | None = None

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
        model = _model_of(self)
        if model.adaptive and self.adapt:
            return AdaptiveModelAgent(model, batch_size)
        return ModelAgent(model, batch_size, bf16)


def _model_of(spec: AgentSpec) -> NavModel:
    """The model of a spec: from a training checkpoint when given, else freshly initialised."""
    import torch

    from mapless.config import from_dict
    from mapless.models import ModelConfig, build_model

    if spec.checkpoint is not None:
        from mapless.checkpoint import load_model as load_trained

        model = load_trained(spec.checkpoint)[0]
    else:
        torch.manual_seed(spec.init_seed)
        model = build_model(from_dict(ModelConfig, spec.model))
    if spec.inner_lr is not None:
        if not model.adaptive or spec.inner_lr <= 0:
            raise MaplessError(
                f"a test-time inner learning rate needs an adaptive model and a rate > 0; got "
                f"{spec.inner_lr} for {type(model).__name__} (adaptive: {model.adaptive})"
            )
        model.config = dataclasses.replace(model.config, inner_lr=spec.inner_lr)
    return model


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

    def under(self, protocol: Protocol, cache_dir: str | Path | None = None) -> LibrarySpec:
        """The same scenes under ``protocol``'s success rule, whatever rule they were trained under
        (a model sees the same observations under both; only success, Done and the optimal lengths
        change), cached in ``cache_dir`` if given."""
        spec = dataclasses.replace(self, sim=protocol.sim(self.sim))
        return spec if cache_dir is None else dataclasses.replace(spec, cache_dir=str(cache_dir))

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
    """Observation fields of the target: the category set's GloVe vector (docs/guide/simulator.md, "Observations")."""
    return TargetFields(category_set)


# -- the episode loop -------------------------------------------------------------------------------
@dataclass(frozen=True)
class EvalSettings:
    """``batch_size`` episodes per worker in lockstep; ``workers`` spawn processes (1: in-process);
    ``seed`` of the action sampling; ``greedy`` argmax actions; ``bf16``: run non-adaptive models
    at training's ``a3c.precision: bf16`` (:mod:`mapless.agent.precision`; 2x faster GCNs on CPUs with
    AVX512-BF16 or AMX; the policies differ from float32 by rounding, so compare models under the
    same setting)."""

    batch_size: int = 32
    workers: int = 2
    seed: int = 0
    greedy: bool = False
    bf16: bool = False
    max_steps: int | None = None
    category_set: str = "mjolnir101"


class Sightings:
    """An episode's :func:`~mapless.evaluate.metrics.sightings` from its trajectory, with the masks of
    its target's poses (visible under the success rule; in the frame) made once per (scene, target,
    instances)."""

    def __init__(self, library: SceneLibrary):
        self.library = library
        self._masks: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, episode: Episode, start_pose: int, poses: Sequence[int], success: bool) -> dict:
        key = (episode.scene, episode.target, episode.target_ids)
        if key not in self._masks:
            data = self.library[episode.scene]
            instances = data.goal_instances(episode.target, episode.target_ids)
            self._masks[key] = (
                data.goal_mask_for_instances(instances),
                data.in_frame_mask_for_instances(instances),
            )
        return sightings(*self._masks[key], start_pose, poses, success)._asdict()


def lacks_sightings(result: EpisodeResult) -> bool:
    """Whether a (cached) result predates one of the sighting fields."""
    return result.first_seen is None or result.ended_in_frame is None or result.stops_passed is None


def with_sightings(
    results: Sequence[EpisodeResult], episodes: Sequence[Episode], library: SceneLibrary
) -> list[EpisodeResult]:
    """``results`` (of ``episodes``, by index) with their sightings (:attr:`EpisodeResult.first_seen`,
    :attr:`~EpisodeResult.ended_in_frame`, :attr:`~EpisodeResult.stops_passed`) filled in from their
    recorded poses where missing (results cached before they were recorded)."""
    sight = Sightings(library)
    filled = []
    for r in results:
        if lacks_sightings(r):
            episode = episodes[r.index]
            if episode.episode_id != r.episode_id:
                raise MaplessError(f"result {r.index} is of episode {r.episode_id}, not {episode.episode_id}")
            r = dataclasses.replace(r, **sight(episode, r.start_pose, r.poses, r.success))
        filled.append(r)
    return filled


class _EvaluationRecorder:
    """The :class:`~mapless.agent.episode_loop.LoopAgent` of :func:`run_episodes`: feeds the set's
    episodes in order, samples ``agent``'s actions from each episode's own uniforms and records every
    finished episode as an :class:`EpisodeResult`."""

    def __init__(
        self,
        agent: Agent,
        episodes: Sequence[Episode],
        indices: Sequence[int],
        settings: EvalSettings,
        batch: int,
        horizon: int,
        sightings: Sightings,
    ):
        self.agent, self.episodes, self.indices, self.settings = agent, episodes, indices, settings
        self.observation_keys = agent.observation_keys
        self.horizon = horizon
        self.queue = list(range(len(episodes)))
        self.queue.reverse()  # pop() from the end takes episodes in set order
        self.slot_item = np.full(batch, -1, dtype=np.int64)
        self.uniforms = np.zeros((batch, horizon + 1))
        self.poses = np.zeros((batch, horizon), dtype=np.int64)
        self.actions = np.zeros((batch, horizon), dtype=np.int8)
        self.failed = np.zeros(batch, dtype=np.int64)
        self.reward = np.zeros(batch)
        self.start_pose = np.zeros(batch, dtype=np.int64)
        self.offsets = np.zeros(batch, dtype=np.int64)
        self.results: list[EpisodeResult] = []
        self.t = np.zeros(batch, dtype=np.int64)  # each slot's step index when it last acted
        self.sightings = sightings

    def feed(self, free: np.ndarray) -> list[Episode]:
        items = [self.queue.pop() for _ in free[: len(self.queue)]]
        self.slot_item[free[: len(items)]] = items
        return [self.episodes[i] for i in items]

    def start(self, slots: np.ndarray, env: BatchedNavEnv) -> None:
        for slot in slots:
            item = int(self.slot_item[slot])
            seed = [self.settings.seed, int(self.indices[item])]
            self.uniforms[slot] = np.random.default_rng(seed).random(self.horizon + 1)
            self.offsets[slot] = env.scene_offset[self.episodes[item].scene]
        self.start_pose[slots] = env.pose[slots] - self.offsets[slots]
        self.failed[slots] = 0
        self.reward[slots] = 0.0
        self.agent.start(slots, env)

    def act(self, obs: dict[str, np.ndarray], slots: np.ndarray, env: BatchedNavEnv) -> np.ndarray:
        # With every slot idle (an adaptive agent waiting for its next k-step boundary) the step is a
        # no-op for the environment but keeps the agent's k-step clock aligned.
        probs = self.agent.policy(obs, env)
        self.t = env.steps.copy()
        if self.settings.greedy:
            return probs.argmax(axis=1)
        return sample_actions(probs, self.uniforms[np.arange(len(probs)), np.minimum(self.t, self.horizon)])

    def after_step(self, slots: np.ndarray, actions: np.ndarray, step: BatchStep, env: BatchedNavEnv) -> None:
        self.agent.after_step(actions, step)
        t, act = self.t, np.flatnonzero(step.active)
        self.poses[act, t[act]] = env.pose[act] - self.offsets[act]
        self.actions[act, t[act]] = actions[act]
        self.failed += step.failed_action
        self.reward += step.reward
        for slot in np.flatnonzero(step.terminated | step.truncated):
            item = int(self.slot_item[slot])
            episode = self.episodes[item]
            length = int(env.steps[slot])
            poses = self.poses[slot, :length]
            self.results.append(
                EpisodeResult(
                    index=int(self.indices[item]),
                    episode_id=episode.episode_id,
                    scene=episode.scene,
                    room_type=room_type_of(episode.scene),
                    target=episode.target,
                    success=bool(step.success[slot]),
                    length=length,
                    optimal_length=int(env.optimal_length[slot]),
                    called_done=bool(step.terminated[slot]),
                    failed_actions=int(self.failed[slot]),
                    reward=float(self.reward[slot]),
                    start_pose=int(self.start_pose[slot]),
                    poses=tuple(poses.tolist()),
                    actions=tuple(self.actions[slot, :length].tolist()),
                    **self.sightings(episode, int(self.start_pose[slot]), poses, bool(step.success[slot])),
                )
            )
            self.slot_item[slot] = -1


def run_episodes(
    agent: Agent,
    library: SceneLibrary,
    episodes: Sequence[Episode],
    indices: Sequence[int],
    settings: EvalSettings,
) -> list[EpisodeResult]:
    """Run ``episodes`` (whose positions in the full set are ``indices``) to the end, in one process,
    through the one episode loop (:class:`~mapless.agent.episode_loop.EpisodeLoop`): a slot whose
    episode ends takes the next one of the set, at the agent's ``start_every`` boundaries."""
    batch = getattr(agent, "batch_size", settings.batch_size)
    scenes = sorted({e.scene for e in episodes})
    env = BatchedNavEnv(
        library, scenes, batch, targets=target_fields(settings.category_set), mode="eval",
        max_steps=settings.max_steps,
    )  # fmt: skip
    horizon = settings.max_steps or max(max_steps_for(library[s].room_type, "eval") for s in scenes)
    recorder = _EvaluationRecorder(agent, episodes, indices, settings, batch, horizon, Sightings(library))
    EpisodeLoop(env, recorder, recorder.feed, start_every=agent.start_every).run()
    return sorted(recorder.results, key=lambda r: r.index)


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
) -> EvalRun:
    """Evaluate ``agent`` on ``episodes`` with ``settings.workers`` spawn workers; results are in
    episode order and identical for any worker count."""
    settings = settings or EvalSettings()
    library = library or LibrarySpec()
    episodes = list(episodes)
    if not episodes:
        raise MaplessError(f"no episodes to evaluate {agent.label} on")
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
        with ProcessPoolExecutor(
            max_workers=workers, mp_context=context, initializer=exit_with_parent, initargs=(os.getpid(),)
        ) as pool:
            out = list(pool.map(_worker, jobs))
    seconds = time.perf_counter() - start
    results = sorted((EpisodeResult.from_dict(d) for part, _, _ in out for d in part), key=lambda r: r.index)
    steps = sum(r.length for r in results)
    return EvalRun(results, seconds, steps, [rss for _, rss, _ in out], max(t for _, _, t in out))
