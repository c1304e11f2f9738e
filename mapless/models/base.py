"""Shared pieces of every navigation model: config, output type and base classes (the layers they are
built from are :mod:`mapless.models.layers`).

Models receive the observation dict of docs/observations.md, the recurrent state ``(h, c)`` and the
previous step's policy (``[B, 6]``), and return :class:`ModelOutput`. Every computation is written
with plain tensor ops on the module's own parameters (the LSTM step included), so
``torch.func.functional_call`` with any parameter dict, and ``torch.func.vmap`` over per-episode
parameters (the meta-learning inner loop, :mod:`mapless.agent.meta`), evaluate the same function.
"""

from __future__ import annotations

import abc
import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import torch
from torch import Tensor, nn

from mapless.actions import NUM_ACTIONS as NUM_ACTIONS  # the policy's width, for every model
from mapless.config import ConfigError
from mapless.knowledge import Knowledge, load_knowledge
from mapless.models.initialisation import glorot_init, init_heads_and_lstm
from mapless.models.layers import lstm_step
from mapless.models.memo import InViewMemo
from mapless.models.roles import ENCODER, LEARNED_LOSS, POLICY, ParameterRoles, assign_roles
from mapless.scenes.catalogue import ROOM_TYPES

GRID = 7  # the 7x7 feature map of docs/observations.md (ResNet-18 conv5 size)
EMBED = 64  # SAVN's per-cell embedding width, reused by every model that follows its layout


class ModelOutput(NamedTuple):
    """``logits [B, 6]`` (softmax gives the policy), ``value [B, 1]``, ``hidden = (h, c)`` each ``[B, H]``."""

    logits: Tensor
    value: Tensor
    hidden: tuple[Tensor, Tensor]


#: What the meta-learning inner step may adapt (:attr:`ModelConfig.adapt`); ``none`` turns the
#: meta-learning off: an adaptive model then trains and acts as a plain recurrent policy.
ADAPT_MODES = ("all", "policy", "none")


@dataclass(frozen=True)
class ModelConfig:
    """Typed construction arguments of every registered model (fields a model does not use are ignored).

    name: registered model name (``mapless models list``).
    category_set: category set of the context vector / graph nodes (``mjolnir101`` or ``all_types``).
    feature_channels: channels of ``obs["features"]``; None = category count + 3 (docs/observations.md);
        512 reproduces the references' ResNet-18 input sizes.
    hidden_size: LSTM width (512 in every reference).
    dropout: dropout rate (SAVN's ``--dropout_rate`` 0.25).
    graph: category graph (``vg`` or ``hierarchical``); None = the model's default.
    hierarchy_rooms: room types whose target<->parent edges enter the ``hierarchical`` graph
        (the paper's "no relationships" ablation removes one).
    inner_lr: inner-loop SGD rate of adaptive models; None = the model's default.
    interaction_steps: k, the rows of the learned interaction loss (SAVN's 6; the TCN's input channels).
    max_inner_updates: inner SGD steps per episode (SAVN's ``--gradient_limit`` 4).
    adapt: what the inner step adapts: ``all`` (SAVN's rule: every parameter outside the learned loss)
        or ``policy`` (θ of the paper's eq. 1-3, ``a_t ~ π(φ(s_t; v), ψ(g; u); θ)``: the fusion, the
        previous-action embedding, LSTM and actor, while the state and target encoders v, u stay
        fixed); ``none``: no meta-learning at all (no inner loop in training, no adaptation at test
        time; the learned loss is built but never used), the same network as a plain recurrent
        policy (the cvmeta ablation's row b); None = the model's default (cvmeta: policy, the
        others: all).
    fusion_channels: output channels of cvmeta's pointwise fusion per category.
    semantic_map: cvmeta also reads the 7x7 semantic feature map that a3c reads (categories, floor,
        walls, depth; docs/observations.md) through a 1x1 convolution to 16 channels, flattened into
        its LSTM input. Not in the paper, whose model sees the scene only through context vectors
        and the graph (the cvmeta ablation's row e).
    gcn_hidden: width of cvmeta's GCN layers before its 64-wide output; None = the node input's width
        (C + 300 = 401, MJOLNIR's object GCN). An ablation knob: the GCN is the one part of cvmeta
        that savn does not have (docs/training.md, "Why cvmeta trains slower than savn").
    target_context: the target descriptor also reads the target category's own context row
        ``[B, x_c, y_c, A_bbox]`` (cvmeta: ``ψ(g, C_g; u)``; a3c, sp, savn, gve, mjolnir_r: the GloVe
        embedding of SAVN's state embedding; spatt: the target query; mjolnir_o, which has no target
        descriptor: the row joins its LSTM input), so "the target is in view, there, this large" is
        one shared input instead of a rule learned per category from the CS column or the feature
        map. Not in any of the papers; off reproduces them (docs/model.md, "Target context").
    reference_extras: also build the references' dead modules (``action_predict_linear``, SAVN's
        ``ll_key``/``ll_linear``, the TCN's unused ``ll_conv2``, MJOLNIR_R's frozen ResNet fc) so that
        parameter counts and state-dict keys match the originals. They never affect outputs.
    """

    name: str = "cvmeta"
    category_set: str = "mjolnir101"
    feature_channels: int | None = None
    hidden_size: int = 512
    dropout: float = 0.25
    graph: str | None = None
    hierarchy_rooms: tuple[str, ...] = ROOM_TYPES
    inner_lr: float | None = None
    interaction_steps: int = 6
    max_inner_updates: int = 4
    fusion_channels: int = 32
    gcn_hidden: int | None = None
    reference_extras: bool = False
    adapt: str | None = None
    target_context: bool = False
    semantic_map: bool = False

    def __post_init__(self) -> None:
        if self.adapt not in (None, *ADAPT_MODES):
            raise ConfigError(f"config key 'model.adapt': {self.adapt!r} is not one of {ADAPT_MODES}")
        # Checked here, not by torch mid-build: a width below 1 is a RuntimeError there, and 0 a
        # model without units that trains without complaint.
        for key in ("hidden_size", "fusion_channels", "interaction_steps", "feature_channels", "gcn_hidden"):
            value = getattr(self, key)
            if value is not None and value < 1:
                raise ConfigError(f"config key 'model.{key}': must be >= 1, got {value}")
        if self.max_inner_updates < 0:
            raise ConfigError(
                f"config key 'model.max_inner_updates': must be >= 0, got {self.max_inner_updates}"
            )
        if not 0 <= self.dropout < 1:  # NaN included; 1 would drop every unit
            raise ConfigError(f"config key 'model.dropout': must lie in [0, 1), got {self.dropout}")


class NavModel(nn.Module):
    """Base class: holds the config and the knowledge-derived sizes; subclasses implement ``forward``."""

    #: Inner-loop learning rate when the model adapts at test time (None: not adaptive).
    default_inner_lr: ClassVar[float | None] = None
    default_graph: ClassVar[str | None] = None
    default_adapt: ClassVar[str] = "all"
    #: What the meta-learning inner loop does with each parameter (:mod:`mapless.models.roles`):
    #: every trainable parameter in exactly one role, checked by :meth:`parameter_role_map`.
    parameter_roles: ClassVar[ParameterRoles] = ParameterRoles()
    description: ClassVar[str] = ""
    #: Whether the model's reference training pays MJOLNIR's hierarchical (parent-object) reward
    #: (``env.parent_reward`` None follows it).
    trains_with_parent_reward: ClassVar[bool] = False

    def __init__(self, config: ModelConfig, knowledge: Knowledge | None = None):
        super().__init__()
        self.config = config
        knowledge = (
            knowledge
            if knowledge is not None
            else load_knowledge(config.category_set, config.hierarchy_rooms)
        )
        self.knowledge = knowledge
        self.num_categories = knowledge.num_categories
        self.glove_dim = knowledge.glove_dim
        self.feature_channels = config.feature_channels or self.num_categories + 3
        self.hidden_size = config.hidden_size

    # -- recurrent state -------------------------------------------------------------------------
    def initial_state(
        self, batch_size: int, device: torch.device | str | None = None
    ) -> tuple[Tensor, Tensor]:
        zeros = torch.zeros(batch_size, self.hidden_size, device=device)
        return zeros, zeros.clone()

    # -- meta-learning interface (overridden by adaptive models) ---------------------------------
    @classmethod
    def is_adaptive(cls) -> bool:
        """Whether the model adapts at test time (it has an inner learning rate); known before it
        is built, as run folders need it."""
        return cls.default_inner_lr is not None

    @property
    def adaptive(self) -> bool:
        """Whether this instance meta-learns and adapts: an adaptive class not built with
        ``adapt: none``."""
        return self.is_adaptive() and self.config.adapt != "none"

    @property
    def inner_lr(self) -> float:
        if not self.adaptive:
            raise TypeError(f"model {self.config.name!r} has no learned interaction loss")
        return self.config.inner_lr if self.config.inner_lr is not None else float(self.default_inner_lr)

    def learned_loss(self, rows: Tensor) -> Tensor:
        """``rows [B, k, H + 6]`` -> interaction loss ``[B]`` (adaptive models only)."""
        raise TypeError(f"model {self.config.name!r} has no learned interaction loss")

    def parameter_role_map(self) -> dict[str, str]:
        """``{trainable parameter name: role}`` of :attr:`parameter_roles`; raises
        :class:`~mapless.models.roles.ParameterRoleError` naming any parameter with no role or several
        (``build_model`` calls it, so a model with one is never built)."""
        return assign_roles(self, self.parameter_roles)

    def learned_loss_parameter_names(self) -> list[str]:
        """φ: the learned-loss parameters (never adapted by the inner step)."""
        return [n for n, role in self.parameter_role_map().items() if role == LEARNED_LOSS]

    def inner_parameter_names(self) -> list[str]:
        """θ adapted by the inner SGD step: the ``policy`` parameters, and under ``adapt: all`` (SAVN's
        rule) the ``encoder`` ones too. ``outer_only`` parameters (critic, dead modules, GVE's graph)
        are the ones SAVN "adapts" with a None gradient, i.e. leaves unchanged."""
        adapted = (POLICY,) if self.adapts_policy_only else (POLICY, ENCODER)
        return [n for n, role in self.parameter_role_map().items() if role in adapted]

    @property
    def adapts_policy_only(self) -> bool:
        """``adapt: policy`` (see :class:`ModelConfig`)."""
        return (self.config.adapt or self.default_adapt) == "policy"

    def graph_name(self) -> str:
        return self.config.graph or str(self.default_graph)

    # -- reuse across steps ----------------------------------------------------------------------
    _in_view_memo: InViewMemo | None = None

    @contextlib.contextmanager
    def memoizing_in_view(self, memo: InViewMemo | None = None) -> Iterator[InViewMemo | None]:
        """Within the block, computations that see the observation only through the in-view
        indicator (the object GCNs, :meth:`per_in_view`) run once per distinct indicator row
        (:mod:`mapless.models.memo`; pass ``memo`` to go on with an earlier block's store).

        Use it only where their parameters stay fixed: a training rollout, an evaluation. Yields None
        and changes nothing when the encoders adapt per episode (``adapt: all``)."""
        if self.adaptive and not self.adapts_policy_only:
            yield None
            return
        memo = memo if memo is not None else InViewMemo()
        previous, self._in_view_memo = self._in_view_memo, memo
        try:
            yield memo
        finally:
            self._in_view_memo = previous

    def per_in_view(self, in_view: Tensor, compute: Callable[[Tensor], Tensor]) -> Tensor:
        """``compute(in_view)`` (rows ``[B, C]`` -> ``[B, ...]``), through the active memo if any."""
        memo = self._in_view_memo
        return compute(in_view) if memo is None else memo(in_view, compute)

    def fixed_term(self, key: str, compute: Callable[[], Tensor]) -> Tensor:
        """``compute()`` of a term that depends on the parameters alone: once per active memo
        (:meth:`InViewMemo.constant`), at every call without one."""
        memo = self._in_view_memo
        return compute() if memo is None else memo.constant(key, compute)


#: The roles of :class:`RecurrentNavModel`'s own modules; subclasses add theirs with ``|``.
RECURRENT_CORE_ROLES = ParameterRoles(policy=("lstm", "actor_linear"), outer_only=("critic_linear",))


class RecurrentNavModel(NavModel, abc.ABC):
    """A model of the form encoder -> ``LSTMCell`` (``self.lstm``) -> actor/critic heads on h.

    Subclasses implement :meth:`encode` (and :meth:`value` if the critic sees more than h), and may
    split off :meth:`describe`. The split lets the meta-learning inner loop run the encoder with
    per-episode weights under ``vmap`` and the LSTM with shared weights plus low-rank per-episode
    updates (:mod:`mapless.agent.meta`).
    """

    parameter_roles = RECURRENT_CORE_ROLES

    def build_recurrent_core(self, lstm_input: int, glorot: bool = True) -> None:
        """The LSTM and the actor/critic heads on h, with SAVN's init: ``glorot`` re-initialises every
        Conv/Linear built so far (encoders included, :func:`glorot_init`), then the heads and LSTM
        biases get theirs (:func:`init_heads_and_lstm`). Call it after the encoders, before any
        module that keeps PyTorch's default init (the learned loss)."""
        self.lstm = nn.LSTMCell(lstm_input, self.hidden_size)
        self.actor_linear = nn.Linear(self.hidden_size, NUM_ACTIONS)
        self.critic_linear = nn.Linear(self.hidden_size, 1)
        if glorot:
            glorot_init(self)
        init_heads_and_lstm(self)

    def core_parameter_names(self) -> list[str]:
        """The parameters of the recurrent core after :meth:`encode` (the LSTM and the actor), which
        the inner loop runs batched rather than per episode."""
        core = [
            *self.lstm.named_parameters(prefix="lstm"),
            *self.actor_linear.named_parameters(prefix="actor_linear"),
        ]
        return [name for name, _ in core]

    def describe(self, obs: dict[str, Tensor]) -> dict[str, Tensor]:
        """The observation-only encoders (the paper's φ(s_t; v) and ψ(g; u)): descriptors that depend
        on neither the recurrent state nor the previous policy, computed with ``encoder`` parameters
        only (:attr:`NavModel.parameter_roles`). Under ``adapt: policy`` the inner loop runs it once for the whole
        batch, outside the per-episode ``vmap``. The default passes the observation through."""
        return obs

    @abc.abstractmethod
    def encode(
        self, described: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        """``(LSTM input [B, D], extra critic input or None)`` from :meth:`describe`'s output."""

    def value(self, h: Tensor, critic_input: Tensor | None) -> Tensor:
        """Critic ``[B, 1]`` on the new hidden state (and the encoder's extra critic input)."""
        return self.critic_linear(h)

    def forward(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> ModelOutput:
        x, critic_input = self.encode(self.describe(obs), hidden, prev_policy)
        h, c = lstm_step(x, hidden, self.lstm)
        return ModelOutput(self.actor_linear(h), self.value(h, critic_input), (h, c))
