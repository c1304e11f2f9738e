"""Typed training configuration (YAML + ``--set key=value``, see :mod:`mapless.config`).

Every check runs in ``__post_init__`` so that a bad value (unknown model, negative learning rate,
unknown scenes, no budget) is a :class:`~mapless.config.ConfigError` naming the key before any scene is
loaded or any worker is started.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import Literal

from mapless.config import ConfigError, from_dict, move_keys
from mapless.errors import MaplessError
from mapless.models.base import ModelConfig
from mapless.models.registry import MODELS, model_class
from mapless.models.settings import unread_setting
from mapless.scenes.catalogue import resolve_scenes
from mapless.scenes.categories import targets
from mapless.sim.config import SimConfig
from mapless.sim.task import TRAIN_MAX_STEPS, RewardConfig


def _require(ok: bool, key: str, message: str) -> None:
    if not ok:
        raise ConfigError(f"config key {key!r}: {message}")


@dataclass(frozen=True)
class LayoutsConfig:
    """Which object arrangements training episodes are drawn on (docs/guide/simulator.md, "Scene variants").

    source: ``default`` (each floor plan's default arrangement only: the paper's protocol),
        ``rearrange2023`` (the Rearrangement dataset's training arrangements, floor plans x01-x20),
        ``gen`` (the procedural generator) or the path of a file in the rearrangement format.
    fraction: share of training episodes drawn on a variant of the episode's floor plan, the rest on
        its default arrangement (0 with ``default``; in (0, 1] otherwise).
    per_scene: variants per floor plan: the source's first usable ones (generator seeds 0, 1, ...).
        Each is a scene of its own in memory and in the cache (about 8 MB, 2-3 s to build).
    """

    source: str = "default"
    fraction: float = 0.0
    per_scene: int = 2

    def __post_init__(self) -> None:
        from mapless.scenes.arrangements import BUILTIN_SOURCES, source_path
        from mapless.scenes.variants import GENERATED

        default = self.source == "default"
        if not (default or self.source == GENERATED or self.source in BUILTIN_SOURCES):
            _require(
                source_path(self.source).is_file(),
                "env.layouts.source",
                f"{self.source!r} is neither default, {GENERATED}, {', '.join(BUILTIN_SOURCES)} nor an arrangement file",
            )
        _require(
            self.fraction == 0 if default else 0 < self.fraction <= 1,
            "env.layouts.fraction",
            f"must be 0 with source default, in (0, 1] otherwise; got {self.fraction}",
        )
        _require(self.per_scene >= 1, "env.layouts.per_scene", f"must be >= 1, got {self.per_scene}")

    def variants(self, scenes: list[str]) -> dict[str, list[str]]:
        """Each floor plan's training variants (none with ``default``)."""
        if self.source == "default":
            return {}
        from mapless.scenes.variants import variants_of

        found = {s: variants_of(s, self.source, self.per_scene) for s in scenes if "@" not in s}
        empty = [s for s, names in found.items() if not names]
        _require(
            not empty, "env.layouts.source", f"{self.source!r} has no arrangement of {', '.join(empty[:5])}"
        )
        return found


@dataclass(frozen=True)
class EnvConfig:
    """Where training episodes come from.

    scenes: split name (``train``), ``split:room``, or comma-separated FloorPlan names.
    target_set: target list per room type (``mjolnir22``, ``savn`` or ``hoz22``,
        mapless.scenes.categories.TARGET_SETS); the evaluation sets follow it (mapless.episodes.evalsets).
    reward: the rewards (:class:`~mapless.sim.task.RewardConfig`: SAVN's step penalty and success
        reward, MJOLNIR's parent-object bonus, its rule and room types, the geodesic-progress
        shaping), the one place a run's reward settings live.
    max_steps: training episode limit (30 in both references).
    cache_dir: cache root, as $MAPLESS_CACHE (scenes go in ``<cache_dir>/scenes/``; None = $MAPLESS_CACHE
        or ~/.cache/mapless).
    offline_dir: a SAVN/MJOLNIR offline data root to train on instead of the built-in simulator
        (docs/guide/interop.md; its 512-channel ResNet maps need ``model.feature_channels=512``).
    sim: simulator parameters (they select the scene cache entry).
    layouts: which arrangements of the floor plans episodes are drawn on (:class:`LayoutsConfig`).
    """

    scenes: str = "train"
    target_set: str = "mjolnir22"
    reward: RewardConfig = field(default_factory=RewardConfig)
    max_steps: int = TRAIN_MAX_STEPS
    cache_dir: str | None = None
    offline_dir: str | None = None
    sim: SimConfig = field(default_factory=SimConfig)
    layouts: LayoutsConfig = field(default_factory=LayoutsConfig)

    def __post_init__(self) -> None:
        try:
            names = resolve_scenes(self.scenes)
        except KeyError as error:  # UnknownNameError is both a MaplessError and a KeyError
            raise ConfigError(f"config key 'env.scenes': {error}") from None
        _require(bool(names), "env.scenes", f"{self.scenes!r} selects no scene")
        try:
            targets(self.target_set)
        except KeyError as error:
            raise ConfigError(f"config key 'env.target_set': {error}") from None
        _require(self.max_steps > 0, "env.max_steps", f"must be positive, got {self.max_steps}")
        _require(
            self.layouts.source == "default" or not self.offline_dir,
            "env.layouts.source",
            "scene variants need the built-in simulator, not an offline data root",
        )

    def scene_list(self) -> list[str]:
        return list(dict.fromkeys(resolve_scenes(self.scenes)))

    def variant_map(self) -> dict[str, list[str]]:
        """Each training floor plan's variants under ``layouts`` (empty: default arrangements only)."""
        return self.layouts.variants(self.scene_list())

    def all_scenes(self) -> list[str]:
        """The training scenes with their variants: what the environment and library must hold."""
        return self.scene_list() + [v for names in self.variant_map().values() for v in names]


@dataclass(frozen=True)
class A3CConfig:
    """The references' A3C (``algo: a3c``): how it runs, SharedAdam's constants (lr 1e-4, betas
    (0.9, 0.999), eps 1e-3, AMSGrad) and the loss constants (γ, τ, entropy β, value coefficient).

    mode: ``batched`` (``batch_size`` episodes in lockstep, one update per batch, per rank under
        torchrun) or ``async`` (the references' Hogwild A3C: ``workers`` processes, one update per
        episode, shared AMSGrad Adam).
    grad_clip: max gradient norm of non-adaptive models (the references clip at 100); 0 = off.
    meta_grad_clip: the same for adaptive models (SAVN applies none: 0).
    precision: ``fp32``, or ``bf16`` for bfloat16 operands in the observation encoders (autocast)
        and the LSTM's weight products (forward, inner steps, weight gradient), where most of the
        arithmetic is; parameters, optimizer and losses stay float32 (:mod:`mapless.agent.precision`,
        docs/guide/training.md "Precision"). Opt-in; PPO trains in float32.
    """

    mode: Literal["batched", "async"] = "batched"
    batch_size: int = 32
    workers: int = 2
    lr: float = 1e-4
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-3
    amsgrad: bool = True
    grad_clip: float = 100.0
    meta_grad_clip: float = 0.0
    gamma: float = 0.99
    tau: float = 1.0
    beta: float = 0.01
    value_coef: float = 0.5
    precision: Literal["fp32", "bf16"] = "fp32"

    def __post_init__(self) -> None:
        _require(
            self.mode in ("batched", "async"), "a3c.mode", f"must be batched or async, got {self.mode!r}"
        )
        _require(self.batch_size >= 1, "a3c.batch_size", f"must be >= 1, got {self.batch_size}")
        _require(self.workers >= 1, "a3c.workers", f"must be >= 1, got {self.workers}")
        _require(_finite(self.lr) and 0 < self.lr <= 1, "a3c.lr", f"must lie in (0, 1], got {self.lr}")
        _require(0 <= self.beta1 < 1 and 0 <= self.beta2 < 1, "a3c.beta1/beta2", "must lie in [0, 1)")
        _require(self.eps > 0, "a3c.eps", f"must be positive, got {self.eps}")
        for key in ("grad_clip", "meta_grad_clip", "beta", "value_coef"):
            value = getattr(self, key)
            _require(
                _finite(value) and value >= 0, f"a3c.{key}", f"must be finite and >= 0 (0 = off), got {value}"
            )
        _require(0 < self.gamma <= 1, "a3c.gamma", f"must lie in (0, 1], got {self.gamma}")
        _require(0 <= self.tau <= 1, "a3c.tau", f"must lie in [0, 1], got {self.tau}")
        _require(
            self.precision in ("fp32", "bf16"),
            "a3c.precision",
            f"must be fp32 or bf16, got {self.precision!r}",
        )


#: The steps the outer loss of adaptive models reads (:attr:`PPOMetaConfig.navigation_loss`).
NAVIGATION_LOSSES = ("episode", "after_interaction")


@dataclass(frozen=True)
class MetaConfig:
    """Meta-learning of adaptive models (savn, gve, spatt, cvmeta), as both algorithms read it.

    first_order: first-order meta-gradient instead of SAVN's second order.
    The inner learning rate, k and the number of inner steps are model settings (``model.inner_lr``,
    ``model.interaction_steps``, ``model.max_inner_updates``) because evaluation adapts with them too;
    what only PPO's meta-learning reads is in ``ppo.meta`` (:class:`PPOMetaConfig`).
    """

    first_order: bool = False


@dataclass(frozen=True)
class PPOMetaConfig:
    """What the PPO trainer's meta-learning reads (``ppo.meta``): only for a model that meta-learns
    (adaptive, ``model.adapt`` not ``none``), and refused for any other.

    navigation_loss: which steps of an episode the outer (navigation) loss reads:
        ``episode``, every step, each with the weights that acted (SAVN's code), or
        ``after_interaction``, only the steps after the first k (the paper's text: L_nav on
        D_nav, the rest of the trajectory; with ``model.max_inner_updates: 1`` that is the paper's
        schedule, one adaptation after the first k steps).
    learned_loss_from_imitation: whether the learned interaction loss φ is meta-trained while the
        imitation term (``ppo.imitation_coef``) is on. Off (default): φ receives no gradient from an
        update whose loss holds the expert's cross-entropy, a signal that does not exist at test
        time, so φ only ever learns to stand in for the navigation loss.
    train_learned_loss: whether φ is meta-trained at all. Off: φ keeps its initialisation, so the
        inner steps still move the fast weights, but along a gradient that nothing has taught (an
        ablation row: what meta-training φ adds to the inner steps; docs/results/ablation.md).
    """

    navigation_loss: str = "episode"
    learned_loss_from_imitation: bool = False
    train_learned_loss: bool = True

    def __post_init__(self) -> None:
        _require(
            self.navigation_loss in NAVIGATION_LOSSES,
            "ppo.meta.navigation_loss",
            f"{self.navigation_loss!r} is not one of {NAVIGATION_LOSSES}",
        )


@dataclass(frozen=True)
class PPOConfig:
    """Recurrent PPO (``algo: ppo``), CleanRL's constants by default.

    envs: environment slots stepped together (per rank); adaptive models play ``envs`` whole
        episodes per update instead of segments.
    steps: segment length (non-adaptive models; adaptive ones run to the episodes' end).
    whole_episodes: non-adaptive models play ``envs`` whole episodes per update too, as the
        adaptive ones always do (each replayed from its first step; a slot whose episode ended
        idles until the update). Off: ``steps``-step segments. The ablation's rows p and q ask whether
        row o's gain over row l is the whole episodes or the updates per frame they bring
        (docs/results/ablation.md).
    epochs, minibatches: passes over each batch of experience, and minibatches per pass (each a
        set of whole slot sequences, so the recurrent state is replayed from the segment's start).
    lr, adam_eps: Adam (``torch.optim.Adam``); ``lr_decay`` anneals lr linearly to 0 over the budget.
    clip: surrogate clip ε; value_clip: clip of the value change (0 = off).
    entropy_coef, value_coef: loss weights; max_grad_norm: gradient-norm clip (0 = off).
    gamma, lam: discount and GAE λ; normalize_advantages: per minibatch.
    imitation_coef: weight of an imitation term, the cross-entropy of the policy to the simulator's
        shortest-path expert on the agent's own steps (DAgger-style); 0 = off, the paper's protocol.
    imitation_frames: the weight falls linearly to 0 over this many frames (0 = constant).
    bootstrap_time_limit: adaptive models' whole episodes cut by the step limit are bootstrapped
        with V of the state they were cut in, as the other models' segments are (off: the
        references' R = 0 there, which makes a blind ``Done`` free near the limit).
    meta: the meta-learning settings only PPO reads (:class:`PPOMetaConfig`).
    """

    envs: int = 64
    steps: int = 32
    whole_episodes: bool = False
    epochs: int = 4
    minibatches: int = 4
    lr: float = 3e-4
    adam_eps: float = 1e-5
    lr_decay: bool = False
    clip: float = 0.2
    value_clip: float = 0.0
    entropy_coef: float = 0.01
    value_coef: float = 0.5
    max_grad_norm: float = 0.5
    gamma: float = 0.99
    lam: float = 0.95
    normalize_advantages: bool = True
    imitation_coef: float = 0.0
    imitation_frames: int = 0
    bootstrap_time_limit: bool = False
    meta: PPOMetaConfig = field(default_factory=PPOMetaConfig)

    def __post_init__(self) -> None:
        _require(
            self.imitation_frames >= 0, "ppo.imitation_frames", f"must be >= 0, got {self.imitation_frames}"
        )
        for key in ("envs", "steps", "epochs", "minibatches"):
            _require(getattr(self, key) >= 1, f"ppo.{key}", f"must be >= 1, got {getattr(self, key)}")
        _require(
            self.minibatches <= self.envs,
            "ppo.minibatches",
            f"{self.minibatches} minibatches of whole slot sequences need at least as many slots "
            f"(ppo.envs = {self.envs})",
        )
        for key in ("lr", "adam_eps"):
            value = getattr(self, key)
            _require(_finite(value) and 0 < value <= 1, f"ppo.{key}", f"must lie in (0, 1], got {value}")
        for key in ("clip", "value_clip", "entropy_coef", "value_coef", "max_grad_norm", "imitation_coef"):
            value = getattr(self, key)
            _require(_finite(value) and value >= 0, f"ppo.{key}", f"must be finite and >= 0, got {value}")
        _require(0 < self.gamma <= 1, "ppo.gamma", f"must lie in (0, 1], got {self.gamma}")
        _require(0 <= self.lam <= 1, "ppo.lam", f"must lie in [0, 1], got {self.lam}")


def _finite(value: float) -> bool:
    return math.isfinite(value)


def _changed_keys(block: object) -> list[str]:
    """The fields of a settings block that differ from its defaults."""
    default = type(block)()
    return [f.name for f in dataclasses.fields(block) if getattr(block, f.name) != getattr(default, f.name)]


#: What a TrainConfig's ``logger`` may list (mapless.train.monitor writes to each).
LOGGERS = ("tensorboard", "wandb")


@dataclass(frozen=True)
class TrainConfig:
    """A training run: the model, its environment and learning settings (the nested configs), then
    how it trains, its budget, where it runs and what it leaves behind (each field's text below)."""

    model: ModelConfig = field(default_factory=ModelConfig)
    env: EnvConfig = field(default_factory=EnvConfig)
    meta: MetaConfig = field(default_factory=MetaConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    a3c: A3CConfig = field(default_factory=A3CConfig)

    algo: Literal["a3c", "ppo"] = "a3c"
    """``ppo`` (recurrent PPO, :class:`PPOConfig`; batched mode) or ``a3c`` (the references' recipe,
    :class:`A3CConfig`: one A3C step per batch of whole episodes, or per episode in async mode).
    Only the chosen algorithm's block may differ from its defaults."""

    episodes: int = 0
    """The budget in episodes; training stops when it or ``frames`` is reached (0 = no limit on this
    one, but one of the two must be set)."""
    frames: int = 0
    """The budget in frames (agent steps), as ``episodes``."""
    max_seconds: float = 0.0
    """Also stop after this much wall-clock training time (0 = no limit; benchmarks and the budgets
    use it; a resumed run gets the full amount again)."""

    seed: int = 1
    """Seeds the episode sampler, the action noise and torch; every torchrun rank and async worker
    draws its own streams from it (``seed_for``: a ``SeedSequence`` of the seed and the rank)."""
    device: str = "cpu"
    """``cpu`` or ``cuda`` (batched mode; async workers always run on the CPU)."""
    threads: int = 0
    """Torch threads of the batched trainer (0 = every core); async workers use 1 each."""
    checkpoint_every: int = 10_000
    """Episodes between checkpoints (a resumable one plus a model snapshot); see ``snapshots``."""
    snapshots: int = 0
    """When > 0, checkpoints follow the run's budget instead of ``checkpoint_every``: one each time
    a ``1/snapshots`` share of any budget it has (``episodes``, ``frames``, ``max_seconds``) has passed
    since the last one. However the run ends, it then keeps at least ``snapshots - 1`` snapshots
    before its final model for checkpoint selection: a slow model stopped by the clock as many as
    a fast one stopped by its frames (a count of episodes gave slow models one)."""
    log_every: int = 100
    """Episodes between TensorBoard / metrics.jsonl records."""
    progress: bool = True
    """Show the tqdm bar."""
    logger: tuple[str, ...] = ("tensorboard",)
    """Where the records go beside ``metrics.jsonl``: ``tensorboard`` and/or ``wandb`` (Weights &
    Biases, the ``wandb`` extra; offline or online as wandb's settings say, e.g. $WANDB_MODE=offline),
    as ``logger: [tensorboard, wandb]``; ``[]``: metrics.jsonl alone. Changes no training (nor the
    run's folder under ``mapless reproduce``)."""

    def __post_init__(self) -> None:
        try:
            model = model_class(self.model.name)
        except MaplessError as error:
            raise ConfigError(f"config key 'model.name': {error}") from None
        _require(self.model.name != "random", "model.name", "the random agent has nothing to train")
        if (unread := unread_setting({**MODELS, self.model.name: model}, self.model)) is not None:
            raise ConfigError(unread)
        _require(self.episodes >= 0, "episodes", f"must be >= 0, got {self.episodes}")
        _require(self.frames >= 0, "frames", f"must be >= 0, got {self.frames}")
        _require(self.episodes > 0 or self.frames > 0, "episodes", "set a budget: episodes or frames > 0")
        _require(
            _finite(self.max_seconds) and self.max_seconds >= 0,
            "max_seconds",
            f"must be finite and >= 0, got {self.max_seconds}",
        )
        _require(self.threads >= 0, "threads", f"must be >= 0, got {self.threads}")
        _require(self.seed >= 0, "seed", f"must be >= 0 (numpy seeds are non-negative), got {self.seed}")
        _require(self.algo in ("a3c", "ppo"), "algo", f"must be a3c or ppo, got {self.algo!r}")
        other = "ppo" if self.algo == "a3c" else "a3c"
        if changed := _changed_keys(getattr(self, other)):
            # An error, not a warning: a setting the run's algorithm never reads would be recorded in
            # its config (and its run-folder hash) as if it had trained with it.
            raise ConfigError(
                f"config key '{other}.{changed[0]}': algo is {self.algo}, which reads only the "
                f"{self.algo}: block; remove the {other}: settings ({', '.join(changed)}) "
                f"or set algo: {other}"
            )
        self._check_ppo_meta_keys(model)
        _require(self.checkpoint_every >= 1, "checkpoint_every", f"must be >= 1, got {self.checkpoint_every}")
        _require(self.snapshots >= 0, "snapshots", f"must be >= 0, got {self.snapshots}")
        _require(self.log_every >= 1, "log_every", f"must be >= 1, got {self.log_every}")
        _require(
            set(self.logger) <= set(LOGGERS) and len(set(self.logger)) == len(self.logger),
            "logger",
            f"must list {' and/or '.join(LOGGERS)}, each at most once, got {list(self.logger)}",
        )
        _require(
            re.fullmatch(r"cpu|cuda(:\d+)?", self.device) is not None,
            "device",
            f"must be 'cpu' or 'cuda[:N]', got {self.device!r}",
        )
        if self.device != "cpu":
            import torch

            _require(
                torch.cuda.is_available(),
                "device",
                f"{self.device!r} asked for, but this PyTorch build sees no CUDA device (torch {torch.__version__})",
            )
        _require(
            self.model.category_set == self.env.sim.category_set,
            "model.category_set",
            f"{self.model.category_set!r} differs from env.sim.category_set {self.env.sim.category_set!r}",
        )

    def _check_ppo_meta_keys(self, model: type) -> None:
        """Refuses ``ppo.meta`` settings for a model that does not meta-learn, which would ignore them
        (under ``algo: a3c`` the whole ``ppo:`` block is refused already)."""
        changed = _changed_keys(self.ppo.meta)
        if self.algo != "ppo" or not changed or (model.is_adaptive() and self.model.adapt != "none"):
            return
        adaptive = ", ".join(n for n, c in MODELS.items() if c.is_adaptive())
        raise ConfigError(
            f"config key 'ppo.meta.{changed[0]}': model {self.model.name!r} (model.adapt "
            f"{self.model.adapt}) does not meta-learn, so the run would ignore it; ppo.meta is read "
            f"for an adaptive model ({adaptive}) whose model.adapt is not none"
        )

    @property
    def mode(self) -> str:
        """How the run trains: ``a3c.mode`` under A3C; PPO always runs batched."""
        return self.a3c.mode if self.algo == "a3c" else "batched"

    @property
    def parent_reward(self) -> bool:
        """``env.reward.parent_reward``, None resolved for the model (its class's
        ``trains_with_parent_reward``)."""
        if self.env.reward.parent_reward is not None:
            return self.env.reward.parent_reward
        return model_class(self.model.name).trains_with_parent_reward

    def replace(self, **changes) -> TrainConfig:
        return dataclasses.replace(self, **changes)


#: Each change of the config's layout since run configs were first stored (docs/changelog.md): what
#: it made and where each moved key lives now, ``(old path, new path)``, oldest change first. A config stored before a
#: change (a checkpoint's, a run folder's config.yaml) is read through it
#: (:func:`stored_train_config`), and ``mapless runs migrate`` recomputes the run-folder names of
#: earlier layouts from it (:mod:`mapless.experiments.migrate`).
LAYOUT_CHANGES: tuple[tuple[str, tuple[tuple[str, str], ...]], ...] = (
    (
        "the a3c: and env.reward: blocks",
        (
            *(
                (f"optim.{k}", f"a3c.{k}")
                for k in ("lr", "beta1", "beta2", "eps", "amsgrad", "grad_clip", "meta_grad_clip")
            ),
            *((f"loss.{k}", f"a3c.{k}") for k in ("gamma", "tau", "beta", "value_coef")),
            *((k, f"a3c.{k}") for k in ("mode", "batch_size", "workers")),
            *(
                (f"env.{k}", f"env.reward.{k}")
                for k in (
                    "step_penalty",
                    "success_reward",
                    "parent_reward",
                    "parent_reward_rule",
                    "progress_reward",
                    "parent_reward_rooms",
                )
            ),
        ),
    ),
    (
        "the ppo.meta: block",
        tuple(
            (f"meta.{k}", f"ppo.meta.{k}")
            for k in ("navigation_loss", "learned_loss_from_imitation", "train_learned_loss")
        ),
    ),
    ("precision in the a3c: block", (("precision", "a3c.precision"),)),
)


def in_current_layout(data: dict) -> dict:
    """A stored training config (plain data) with the keys of every earlier layout moved to where
    they live now (:data:`LAYOUT_CHANGES`); a config in today's layout comes back unchanged."""
    return move_keys(data, [move for _, moves in LAYOUT_CHANGES for move in moves])


def stored_train_config(data: dict) -> TrainConfig:
    """The TrainConfig of a stored config in today's layout or an earlier one."""
    return from_dict(TrainConfig, in_current_layout(data))


def train_config_from(data: dict) -> TrainConfig:
    """The TrainConfig of a config being written (files and ``--set``), which must be in today's
    layout: a key of an earlier one is refused, naming where it lives now."""
    for change, moves in LAYOUT_CHANGES:
        for old, new in moves:
            node: object = data
            for part in old.split("."):
                node = node.get(part, _ABSENT) if isinstance(node, dict) else _ABSENT
            if node is not _ABSENT:
                raise ConfigError(f"config key {old!r} is now {new!r} (the layout change: {change})")
    return from_dict(TrainConfig, data)


_ABSENT = object()
