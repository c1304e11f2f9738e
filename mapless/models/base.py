"""Shared pieces of every navigation model: config, output type and base classes (the layers they are
built from are :mod:`mapless.models.layers`).

Models receive the observation dict of docs/guide/simulator.md, "Observations", the recurrent state ``(h, c)`` and the
previous step's policy (``[B, 6]``), and return :class:`ModelOutput`. Every computation is written
with plain tensor ops on the module's own parameters (the LSTM step included), so
``torch.func.functional_call`` with any parameter dict, and ``torch.func.vmap`` over per-episode
parameters (the meta-learning inner loop, :mod:`mapless.agent.meta`), evaluate the same function.

A recurrent policy (:class:`RecurrentNavModel`) owns every form of its step, so that agent/ and
train/ call them and never compute with its submodules: ``forward``; :meth:`~RecurrentNavModel.
rollout_step` (through a rollout's LSTM weight products, at a precision); :meth:`~RecurrentNavModel.
replay` (a recorded segment, time-batched); :meth:`~RecurrentNavModel.fast_step` (per-episode fast
weights); :meth:`~NavModel.predict_values` (the value alone). They share the encoder stage and the
heads, and differ only in how the gate pre-activations are formed.
"""

from __future__ import annotations

import abc
import contextlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import ClassVar, NamedTuple, Protocol

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.func import functional_call, vmap
from torch.profiler import record_function

from mapless.actions import NUM_ACTIONS as NUM_ACTIONS  # the policy's width, for every model
from mapless.config import ConfigError
from mapless.knowledge import Knowledge, load_knowledge
from mapless.models.initialisation import glorot_init, init_heads_and_lstm
from mapless.models.layers import lstm_state_from_gates, lstm_step, scatter_rows
from mapless.models.memo import InViewMemo
from mapless.models.roles import ENCODER, LEARNED_LOSS, POLICY, ParameterRoles, assign_roles
from mapless.observations import GRID as GRID  # the feature map's side, for every model
from mapless.scenes.catalogue import ROOM_TYPES

EMBED = 64  # SAVN's per-cell embedding width, reused by every model that follows its layout


class ModelOutput(NamedTuple):
    """``logits [B, 6]`` (softmax gives the policy), ``value [B, 1]``, ``hidden = (h, c)`` each ``[B, H]``."""

    logits: Tensor
    value: Tensor
    hidden: tuple[Tensor, Tensor]


class FastStep(NamedTuple):
    """:meth:`RecurrentNavModel.fast_step`'s output, with what the inner step differentiates: the gate
    pre-activations ``gates [B, 4H]`` and the LSTM's input row ``inputs [B, D + H] = [x || h]``."""

    output: ModelOutput
    gates: Tensor
    inputs: Tensor


class WeightProducts(Protocol):
    """The LSTM's weight products of one rollout (:class:`mapless.agent.rollout_lstm.RolloutLstm`):
    ``gates(x, h)`` is ``([x || h], [x || h] · Wᵀ)`` with ``dtype`` operands, biases not added;
    ``input_gates(x)`` and ``hidden_gates(h)`` are its two terms ``x · W_ihᵀ`` and ``h · W_hhᵀ``."""

    dtype: torch.dtype

    def gates(self, x: Tensor, h: Tensor) -> tuple[Tensor, Tensor]: ...

    def input_gates(self, x: Tensor) -> Tensor: ...

    def hidden_gates(self, h: Tensor) -> Tensor: ...


#: The LSTM matrices (of :class:`RecurrentNavModel`), whose per-episode updates the meta-learning
#: inner loop keeps in low rank instead of as per-episode copies (:mod:`mapless.agent.fast_weights`).
LOW_RANK = ("lstm.weight_ih", "lstm.weight_hh")


#: What the meta-learning inner step may adapt (:attr:`ModelConfig.adapt`); ``none`` turns the
#: meta-learning off: an adaptive model then trains and acts as a plain recurrent policy.
ADAPT_MODES = ("all", "policy", "none")


@dataclass(frozen=True)
class ModelConfig:
    """Typed construction arguments of every registered model. A field the chosen model does not read
    (``NavModel.settings``) is refused by the training config rather than ignored
    (:mod:`mapless.models.settings`).

    name: a model name (``mapless models list``), or the import path ``package.module:Class`` of a
        model in one's own package (:func:`mapless.models.registry.model_class`).
    category_set: category set of the context vector / graph nodes (``mjolnir101`` or ``all_types``).
    feature_channels: channels of ``obs["features"]``; None = category count + 3 (docs/guide/simulator.md, "Observations");
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
        walls, depth; docs/guide/simulator.md, "Observations") through a 1x1 convolution to 16 channels, flattened into
        its LSTM input. Not in the paper, whose model sees the scene only through context vectors
        and the graph (the cvmeta ablation's row e).
    context_distance: the context rows a model reads gain a column, the distance (m) to the
        category's nearest in-view instance (0 when none is in view; ``obs["context_distance"]``):
        what a depth reading at each box adds. cvmeta: every category's context vector and its
        target row; a3c, savn, sp, gve, mjolnir_r: the target row (with ``target_context``). Not in
        any paper, whose boxes carry no depth: cvmeta's false Dones are `Done`s with the target in
        the frame beyond the success rule's 1.5 m (docs/results/learning.md).
    gcn_hidden: width of cvmeta's GCN layers before its 64-wide output; None = the node input's width
        (C + 300 = 401, MJOLNIR's object GCN). An ablation knob: the GCN is the one part of cvmeta
        that savn does not have (docs/guide/training.md, "Why cvmeta trains slower than savn").
    target_context: the target descriptor also reads the target category's own context row
        ``[B, x_c, y_c, A_bbox]`` (cvmeta: ``ψ(g, C_g; u)``; a3c, sp, savn, gve, mjolnir_r: the GloVe
        embedding of SAVN's state embedding; spatt: the target query; mjolnir_o, which has no target
        descriptor: the row joins its LSTM input), so "the target is in view, there, this large" is
        one shared input instead of a rule learned per category from the CS column or the feature
        map. Not in any of the papers; off reproduces them (docs/guide/models.md, "Target context").
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
    context_distance: bool = False

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
    #: The :class:`ModelConfig` keys the model reads, each with the condition under which it does
    #: (:mod:`mapless.models.settings`): a key it does not read is refused, not ignored.
    settings: ClassVar[dict[str, str]] = {}
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

    def predict_values(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> Tensor:
        """``[B]`` V of the state, without a graph (the value a truncation is bootstrapped with)."""
        with torch.no_grad():
            return self(obs, hidden, prev_policy).value.reshape(-1)

    # -- reuse across steps ----------------------------------------------------------------------
    _in_view_memo: InViewMemo | None = None
    #: The model reads the in-view row only in :meth:`RecurrentNavModel.critic_context`, with
    #: parameters no inner step adapts: the memo holds under ``adapt: all`` too.
    in_view_outside_encoders: ClassVar[bool] = False

    @contextlib.contextmanager
    def memoizing_in_view(self, memo: InViewMemo | None = None) -> Iterator[InViewMemo | None]:
        """Within the block, computations that see the observation only through the in-view
        indicator (the object GCNs, :meth:`per_in_view`) run once per distinct indicator row
        (:mod:`mapless.models.memo`; pass ``memo`` to go on with an earlier block's store).

        Use it only where their parameters stay fixed: a training rollout, an evaluation. Yields None
        and changes nothing when the encoders adapt per episode (``adapt: all``), unless the model's
        only in-view computations are outside them (:attr:`in_view_outside_encoders`)."""
        if self.adaptive and not self.adapts_policy_only and not self.in_view_outside_encoders:
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
    #: :meth:`encode` reads the recurrent state (spatt's memory query): its steps cannot be encoded
    #: ahead of the recurrence (:meth:`encoded_steps`), only one at a time.
    encoder_reads_state: ClassVar[bool] = False

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

    def critic_context(self, obs: dict[str, Tensor]) -> Tensor | None:
        """An extra critic input of the observation alone, from parameters no inner step adapts
        (``outer_only``), or None (the default: the critic reads what :meth:`encode` returns). Where
        a model has one, it is computed once over every row of a call (episodes and steps), with the
        shared weights, outside the per-episode encoders; its in-view computations go through the
        memo even when the encoders adapt (:meth:`memoizing_in_view`)."""
        return None

    def value(self, h: Tensor, critic_input: Tensor | None) -> Tensor:
        """Critic ``[B, 1]`` on the new hidden state (and the encoder's extra critic input)."""
        return self.critic_linear(h)

    @property
    def recurrent_cell(self) -> nn.LSTMCell:
        """The LSTM cell whose matrices a rollout's weight products read (the caller makes a
        :class:`~mapless.agent.rollout_lstm.RolloutLstm` of it once per rollout and passes it to
        :meth:`rollout_step` or :meth:`fast_step`)."""
        return self.lstm

    # -- the step, in each of its forms ----------------------------------------------------------
    def forward(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> ModelOutput:
        x, critic_input = self._encoded(obs, hidden, prev_policy)
        h, c = lstm_step(x, hidden, self.lstm)
        return self._output(h, c, critic_input)

    def rollout_step(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor, lstm: WeightProducts
    ) -> ModelOutput:
        """One step with the LSTM's weight products taken by ``lstm`` (recorded for its once-summed
        weight gradient when it records: training), at its compute dtype, the one meaning of
        ``bf16`` in this project (:mod:`mapless.agent.precision`): the encoders under autocast to
        that dtype, the gates, state and heads in the parameters' float32. The training actor and
        the evaluator's bf16 agent step through it."""
        return self.fast_step({}, obs, hidden, prev_policy, lstm).output

    def fast_step(
        self,
        fast: dict[str, Tensor],
        obs: dict[str, Tensor],
        hidden: tuple[Tensor, Tensor],
        prev_policy: Tensor,
        lstm: WeightProducts,
        low_rank: Callable[[Tensor], Tensor] | None = None,
    ) -> FastStep:
        """:meth:`rollout_step` with each episode's own weights: ``fast`` maps parameter names to
        per-episode ``[B, ...]`` tensors (the names it lacks read the shared parameters; the
        :data:`LOW_RANK` matrices are never in it), and ``low_rank`` maps the step's ``[x || h]`` to
        the episodes' updates of the gates from their LSTM matrices (None before any inner step)."""
        x, critic_input = self._encoded(obs, hidden, prev_policy, self._reduced(lstm), fast)
        inputs, product = lstm.gates(x, hidden[0])
        return self._fast_core(fast, inputs, product, hidden[1], critic_input, low_rank)

    def encoded_steps(
        self, fast: dict[str, Tensor], obs: dict[str, Tensor], prev_policy: Tensor, lstm: WeightProducts
    ) -> tuple[Tensor, Tensor | None]:
        """:meth:`fast_step`'s encoder stage for ``L`` steps of every episode at once: ``obs`` and
        ``prev_policy`` are ``[B, L, ...]``, ``fast`` per-episode ``[B, ...]`` as in :meth:`fast_step`
        (fixed over the L steps); returns ``(x [B, L, D], critic input [B, L, ...] or None)``, each
        row equal to that step's :meth:`fast_step` encoding. Only for encoders that do not read the
        recurrent state (not :attr:`encoder_reads_state`)."""
        if self.encoder_reads_state:
            raise TypeError(
                f"model {self.config.name!r} encodes from the recurrent state, one step at a time"
            )
        batch, steps = prev_policy.shape[:2]
        hidden = self.initial_state(batch * steps, prev_policy.device)  # unread by these encoders
        hidden = tuple(t.view(batch, steps, -1) for t in hidden)
        return self._encoded(obs, hidden, prev_policy, self._reduced(lstm), fast, steps=True)

    def fast_step_encoded(
        self,
        fast: dict[str, Tensor],
        x: Tensor,
        input_gates: Tensor,
        critic_input: Tensor | None,
        hidden: tuple[Tensor, Tensor],
        lstm: WeightProducts,
        low_rank: Callable[[Tensor], Tensor] | None = None,
    ) -> FastStep:
        """:meth:`fast_step` from its encoding ``x`` (:meth:`encoded_steps`) and ``x``'s share of the
        gates ``input_gates = lstm.input_gates(x)``, which a caller takes for many steps at once: the
        step reads only ``weight_hh`` (``lstm.hidden_gates``)."""
        inputs = torch.cat([x, hidden[0]], dim=-1)
        product = input_gates + lstm.hidden_gates(hidden[0])
        return self._fast_core(fast, inputs, product, hidden[1], critic_input, low_rank)

    def _fast_core(
        self,
        fast: dict[str, Tensor],
        inputs: Tensor,
        product: Tensor,
        c: Tensor,
        critic_input: Tensor | None,
        low_rank: Callable[[Tensor], Tensor] | None,
    ) -> FastStep:
        """The step after the weight products ``product = [x || h] · Wᵀ``: biases, low-rank
        updates, the cell state and the heads."""
        gates = product + self._weight("lstm.bias_ih", fast) + self._weight("lstm.bias_hh", fast)
        if low_rank is not None:
            gates = gates + low_rank(inputs)
        h, c = lstm_state_from_gates(gates, c)
        return FastStep(self._output(h, c, critic_input, fast), gates, inputs)

    def _reduced(self, lstm: WeightProducts) -> torch.dtype | None:
        """The encoders' autocast dtype under ``lstm``'s products (None: the parameters' own)."""
        return None if lstm.dtype == self.lstm.weight_ih.dtype else lstm.dtype

    def replay(
        self,
        obs: dict[str, Tensor],
        prev_policy: Tensor,
        starts: Tensor,
        hidden: tuple[Tensor, Tensor],
        acted: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """``(logits [T, B, A], values [T, B])`` over a recorded segment (the PPO update's forward).

        A segment holds, per environment slot, ``T`` consecutive steps that may span several episodes:
        ``starts [T, B]`` marks a step that opened a new episode, where the recurrent state restarts
        from zeros. ``obs`` is ``[T, B, ...]``; ``prev_policy [T, B, 6]`` is replayed as it was
        recorded while acting (under PPO it is part of the observation), so for models whose encoder
        does not read the recurrent state (every non-adaptive model) the encoder runs once over all
        ``T · B`` rows and the LSTM's input product ``W_ih x`` is one matrix product; only ``W_hh h``
        is computed step by step. The values are those of ``T`` calls of ``forward`` up to rounding
        (tests/test_ppo.py). ``hidden``: ``(h, c)`` ``[B, H]`` before the first step. ``acted [T, B]``
        (bool): the steps a slot took; only those are encoded (whole episodes leave a slot idle after
        its end), and the outputs of the others are meaningless, for the loss to mask out."""
        steps, batch = starts.shape
        flat = {key: value.flatten(0, 1) for key, value in obs.items()}
        flat_policy = prev_policy.flatten(0, 1)
        rows = None if acted is None else acted.flatten().nonzero().squeeze(1)
        if rows is not None:
            flat = {key: value.index_select(0, rows) for key, value in flat.items()}
            flat_policy = flat_policy.index_select(0, rows)
        flat_hidden = self.initial_state(len(flat_policy), prev_policy.device)  # unread by these encoders
        cell = self.lstm
        # The labels name the parts in profiles (bench/frame_cost.py); they cost nothing otherwise.
        with record_function("encoder"):
            x, critic_input = self._encoded(flat, flat_hidden, flat_policy)
            if rows is not None:
                x = scatter_rows(x, rows, steps * batch)
                critic_input = (
                    None if critic_input is None else scatter_rows(critic_input, rows, steps * batch)
                )
            input_gates = F.linear(x, cell.weight_ih, cell.bias_ih + cell.bias_hh).view(steps, batch, -1)
        keep = (~starts).to(x.dtype).unsqueeze(-1)
        h, c = hidden
        outputs = []
        with record_function("lstm"):
            for t in range(steps):
                h, c = h * keep[t], c * keep[t]
                h, c = lstm_state_from_gates(input_gates[t] + F.linear(h, cell.weight_hh), c)
                outputs.append(h)
        with record_function("heads"):
            logits, values = self._heads(torch.stack(outputs).flatten(0, 1), critic_input)
        return logits.view(steps, batch, -1), values.view(steps, batch)

    # -- the parts every form shares ---------------------------------------------------------------
    def _encoded(
        self,
        obs: dict[str, Tensor],
        hidden: tuple[Tensor, Tensor],
        prev_policy: Tensor,
        dtype: torch.dtype | None = None,
        fast: dict[str, Tensor] | None = None,
        steps: bool = False,
    ) -> tuple[Tensor, Tensor | None]:
        """``(LSTM input, critic input)``: :meth:`_encoded_inputs`, with :meth:`critic_context` as
        the critic input where the model has one: computed once over all rows, with the shared
        weights, outside the per-episode encoders."""
        x, critic_input = self._encoded_inputs(obs, hidden, prev_policy, dtype, fast, steps)
        if critic_input is not None or type(self).critic_context is RecurrentNavModel.critic_context:
            return x, critic_input
        # Rows of steps as one batch; a single step's obs as given (the probe records its keys).
        flat = {key: value.flatten(0, 1) for key, value in obs.items()} if steps else obs
        with _autocast(dtype, prev_policy.device):
            context = self.critic_context(flat)
        context = context if dtype is None else _like(context, hidden[0])
        return x, context.unflatten(0, prev_policy.shape[:2]) if steps else context

    def _encoded_inputs(self, obs, hidden, prev_policy, dtype, fast, steps) -> tuple[Tensor, Tensor | None]:
        """:meth:`_encoded`'s arguments. ``encode(describe(obs))``: under autocast to a reduced ``dtype`` with the result back in
        the state's dtype, and per episode under ``vmap`` where ``fast`` holds encoder weights.
        ``steps``: every input has a second dimension of steps (``[B, L, ...]``, one episode's
        weights for all of them), and so have the results."""
        per_episode = {}
        if fast:
            core = set(self.core_parameter_names())  # run batched, after the encoder
            per_episode = {f"model.{n}": w for n, w in fast.items() if n not in core}
        if steps and not per_episode:  # the same weights for every row: one batch of B · L rows
            shape = prev_policy.shape[:2]
            flat = {key: value.flatten(0, 1) for key, value in obs.items()}
            x, critic_input = self._encoded_inputs(
                flat, tuple(t.flatten(0, 1) for t in hidden), prev_policy.flatten(0, 1), dtype, None, False
            )
            return x.unflatten(0, shape), None if critic_input is None else critic_input.unflatten(0, shape)
        if dtype is None and not per_episode:
            return self.encode(self.describe(obs), hidden, prev_policy)
        with _autocast(dtype, prev_policy.device):
            if not per_episode:
                x, critic_input = self.encode(self.describe(obs), hidden, prev_policy)
            else:
                x, critic_input = self._encoded_per_episode(per_episode, obs, hidden, prev_policy, steps)
        if dtype is None:
            return x, critic_input
        return _like(x, hidden[0]), _like(critic_input, hidden[0])

    def _encoded_per_episode(
        self,
        weights: dict[str, Tensor],
        obs: dict[str, Tensor],
        hidden: tuple[Tensor, Tensor],
        prev_policy: Tensor,
        steps: bool = False,
    ) -> tuple[Tensor, Tensor | None]:
        """The encoder with episode b's weights ``weights[·][b]`` on row b (on its L rows ``[b, :]``
        where ``steps``), as ``vmap`` over ``functional_call``. Under ``adapt: policy``
        :meth:`describe` reads shared weights only: one batched call instead of B under vmap."""
        describe_batched = self.adapts_policy_only
        encoder = _Encoder(self, describe=not describe_batched)

        def one_episode(weights, episode_obs, h, c, policy):
            if steps:  # the episode's rows are a batch already
                x, extra = functional_call(encoder, weights, (episode_obs, (h, c), policy))
                return (x,) if extra is None else (x, extra)
            single = {key: value.unsqueeze(0) for key, value in episode_obs.items()}
            x, extra = functional_call(
                encoder, weights, (single, (h.unsqueeze(0), c.unsqueeze(0)), policy.unsqueeze(0))
            )
            return (x[0],) if extra is None else (x[0], extra[0])

        if describe_batched and steps:
            shape = prev_policy.shape[:2]
            described = self.describe({key: value.flatten(0, 1) for key, value in obs.items()})
            obs = {key: value.unflatten(0, shape) for key, value in described.items()}
        elif describe_batched:
            obs = self.describe(obs)
        encoded = vmap(one_episode, randomness="different")(weights, obs, hidden[0], hidden[1], prev_policy)
        return encoded[0], (encoded[1] if len(encoded) > 1 else None)

    def _heads(
        self, h: Tensor, critic_input: Tensor | None, fast: dict[str, Tensor] | None = None
    ) -> tuple[Tensor, Tensor]:
        """``(logits, value)`` on the new hidden state; the actor per episode where ``fast`` holds it."""
        weight, bias = self._weight("actor_linear.weight", fast), self._weight("actor_linear.bias", fast)
        if weight.dim() == 3:
            logits = torch.einsum("bh,bah->ba", h, weight) + bias
        else:
            logits = F.linear(h, weight, bias)
        return logits, self.value(h, critic_input)

    def _output(
        self, h: Tensor, c: Tensor, critic_input: Tensor | None, fast: dict[str, Tensor] | None = None
    ) -> ModelOutput:
        return ModelOutput(*self._heads(h, critic_input, fast), (h, c))

    def _weight(self, name: str, fast: dict[str, Tensor] | None) -> Tensor:
        """The per-episode ``fast[name]``, or the shared parameter where the episodes do not adapt it."""
        if fast and name in fast:
            return fast[name]
        # Not get_parameter: under functional_call the attribute is a plain tensor, not a Parameter.
        module, _, attribute = name.rpartition(".")
        return getattr(self.get_submodule(module), attribute)


class _Encoder(nn.Module):
    """``model.encode`` (after ``model.describe`` unless that runs outside) as a module's forward, so
    that ``functional_call`` can swap its weights. Made per call: as an attribute of the model it
    would be a submodule, in its state dict."""

    def __init__(self, model: RecurrentNavModel, describe: bool):
        super().__init__()
        self.model = model
        self.describe = describe

    def forward(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        described = self.model.describe(obs) if self.describe else obs
        return self.model.encode(described, hidden, prev_policy)


def _autocast(dtype: torch.dtype | None, device: torch.device) -> contextlib.AbstractContextManager:
    """Autocast to ``dtype`` on ``device``'s type (a no-op context for None)."""
    return torch.autocast(device.type, dtype=dtype or torch.bfloat16, enabled=dtype is not None)


def _like(x: Tensor | None, reference: Tensor) -> Tensor | None:
    """``x`` (an autocast output) back in the dtype of the rollout's state ``reference``."""
    return x if x is None or x.dtype == reference.dtype else x.to(reference.dtype)
