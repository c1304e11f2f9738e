"""Shared pieces of every navigation model: config, output type, base class, layers and init.

Models receive the observation dict of docs/observations.md, the recurrent state ``(h, c)`` and the
previous step's policy (``[B, 6]``), and return :class:`ModelOutput`. Every computation is written
with plain tensor ops on the module's own parameters (the LSTM step included), so
``torch.func.functional_call`` with any parameter dict, and ``torch.func.vmap`` over per-episode
parameters (the meta-learning inner loop, :mod:`mapless.agent.meta`), evaluate the same function.
"""

from __future__ import annotations

import abc
import contextlib
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapless.config import ConfigError
from mapless.knowledge import Knowledge, load_knowledge
from mapless.models.memo import InViewMemo
from mapless.models.roles import ENCODER, LEARNED_LOSS, POLICY, ParameterRoles, assign_roles
from mapless.scenes.catalogue import ROOM_TYPES
from mapless.sim.scene_data import NUM_ACTIONS as NUM_ACTIONS  # the policy's width, for every model

GRID = 7  # the 7x7 feature map of docs/observations.md (ResNet-18 conv5 size)
EMBED = 64  # SAVN's per-cell embedding width, reused by every model that follows its layout


class ModelOutput(NamedTuple):
    """``logits [B, 6]`` (softmax gives the policy), ``value [B, 1]``, ``hidden = (h, c)`` each ``[B, H]``."""

    logits: Tensor
    value: Tensor
    hidden: tuple[Tensor, Tensor]


#: What the meta-learning inner step may adapt (:attr:`ModelConfig.adapt`).
ADAPT_MODES = ("all", "policy")


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
        fixed); None = the model's default (cvmeta: policy, the others: all).
    fusion_channels: output channels of cvmeta's pointwise fusion per category.
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

    def __post_init__(self) -> None:
        if self.adapt not in (None, *ADAPT_MODES):
            raise ConfigError(f"config key 'model.adapt': {self.adapt!r} is not one of {ADAPT_MODES}")
        if self.gcn_hidden is not None and self.gcn_hidden < 1:
            raise ConfigError(f"config key 'model.gcn_hidden': {self.gcn_hidden} is not a positive width")


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
    @property
    def adaptive(self) -> bool:
        return self.default_inner_lr is not None

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


# -- layers --------------------------------------------------------------------------------------
def lstm_step(x: Tensor, hidden: tuple[Tensor, Tensor], cell: nn.LSTMCell) -> tuple[Tensor, Tensor]:
    """``nn.LSTMCell`` math (gate order i, f, g, o) written out so that it works under vmap with
    per-episode weights and under functional_call."""
    h, c = hidden
    gates = F.linear(x, cell.weight_ih, cell.bias_ih) + F.linear(h, cell.weight_hh, cell.bias_hh)
    return lstm_state_from_gates(gates, c)


def lstm_state_from_gates(gates: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """``(h', c')`` from the gate pre-activations ``[B, 4H]`` (order i, f, g, o) and the cell state."""
    i, f, g, o = gates.chunk(4, dim=-1)
    c_next = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
    h_next = torch.sigmoid(o) * torch.tanh(c_next)
    return h_next, c_next


def shared_row_gcn_layer(adjacency: Tensor, in_view: Tensor, shared: Tensor, layer: nn.Linear) -> Tensor:
    """``layer(Â · [in_view repeated for every node || F])``, node-major ``[C, B, out]``, given
    ``shared = shared_gcn_term(Â, F, layer)``: the first layer of MJOLNIR's object GCN, without
    forming its ``[B, C, C + D]`` input.

    Every node's row starts with the same in-view vector ``v``, so ``Â · [1 vᵀ]`` is
    ``rowsum(Â) vᵀ``: the layer is ``rowsum(Â) ⊗ (W_v v) + Â · F · W_Fᵀ`` (exact up to rounding),
    and the second term depends on the parameters alone, so callers compute it once for as long as
    they stay fixed (:meth:`NavModel.fixed_term`). The outer product is a matrix product with one
    column, and the shared term is added in place: the ``[C, B, out]`` result is written once, in the
    products' dtype (bfloat16 under autocast), and its backward reduces the gradient with two
    matrix-vector products instead of forming two more tensors of its size. Callers may apply their
    activation in place.
    """
    per_episode = in_view @ layer.weight[:, : in_view.shape[-1]].T  # [B, out]
    nodes, (batch, width) = adjacency.shape[0], per_episode.shape
    outer = torch.mm(adjacency.sum(-1, keepdim=True), per_episode.reshape(1, batch * width))
    out = outer.view(nodes, batch, width).add_(shared.unsqueeze(1).to(outer.dtype))
    return out if layer.bias is None else out.add_(layer.bias.to(out.dtype))


def shared_gcn_term(adjacency: Tensor, node_features: Tensor, layer: nn.Linear) -> Tensor:
    """``Â · F · W_Fᵀ`` ``[C, out]``, the batch-independent term of :func:`shared_row_gcn_layer`
    (``F``: node features ``[C, D]``; ``W_F``: the last ``D`` columns of ``layer``, which read them)."""
    return (adjacency @ node_features) @ layer.weight[:, -node_features.shape[-1] :].T


def propagate(adjacency: Tensor, x: Tensor) -> Tensor:
    """``Â · X`` of node-major features ``[C, B, F]``: one matrix product with no transposes.

    The GCNs keep their activations node-major because both of their products are then plain
    matrix products (``Â`` on the left of ``[C, B·F]``, ``W`` on the right of ``[C·B, F]``); the
    batch-major layout made every ``Â ·`` a transpose copy and a batched product."""
    return (adjacency @ x.reshape(x.shape[0], -1)).reshape(x.shape)


def gcn_layer(adjacency: Tensor, x: Tensor, layer: nn.Linear) -> Tensor:
    """``layer(Â · X)`` of node-major features ``[C, B, F]``, with ``Â`` applied on the narrower side.

    For a bias-free layer ``(Â X) Wᵀ = Â (X Wᵀ)``, so a narrowing layer (MJOLNIR's 401 -> 5, Scene
    Priors' 1024 -> 1) propagates its output instead of its input: the same values, up to rounding,
    at a fraction of the product with Â."""
    if layer.bias is None and layer.out_features < layer.in_features:
        return propagate(adjacency, layer(x))
    return layer(propagate(adjacency, x))


def tile(vector: Tensor, *spatial: int) -> Tensor:
    """``[B, D]`` -> ``[B, D, *spatial]`` by broadcasting (SAVN tiles embeddings over the 7x7 map)."""
    return vector.reshape(*vector.shape, *([1] * len(spatial))).expand(*vector.shape, *spatial)


def pointwise_conv(conv: nn.Conv1d | nn.Conv2d, x: Tensor) -> Tensor:
    """``conv(x)`` of a kernel-size-1 convolution, computed as a product over channels.

    The same values; but under ``vmap`` with per-episode weights (the meta-learning inner loop) it
    batches into one matrix product, where a convolution falls back to one call per episode."""
    y = torch.matmul(conv.weight.flatten(1), x.flatten(2))  # [B, out, positions]
    if conv.bias is not None:
        y = y + conv.bias.unsqueeze(-1)
    return y.unflatten(2, x.shape[2:])


def pointwise_conv_of_parts(conv: nn.Conv1d, maps: list[Tensor], vectors: list[Tensor]) -> Tensor:
    """``pointwise_conv(conv, cat([*maps, *tiled vectors], dim=1))`` without the concatenation.

    ``maps`` are ``[B, D_i, P]``, ``vectors`` ``[B, D_j]`` (constant over the P positions, as tiled
    embeddings are). The weight's column blocks multiply their own part, and a vector's block is a
    product with the vector, once instead of at every position. The same values up to rounding; and
    under the second-order inner loop, whose double backward of a concatenation scatters every
    part's slice into a zero tensor of the full ``[B, D, P]`` size, it saves that traffic too."""
    weight = conv.weight.flatten(1)  # [out, sum of D]
    blocks = weight.split([part.shape[1] for part in (*maps, *vectors)], dim=1)
    map_blocks, vector_blocks = blocks[: len(maps)], blocks[len(maps) :]
    y = sum(torch.matmul(w, part) for w, part in zip(map_blocks, maps, strict=True))  # [B, out, P]
    shift = sum(part @ w.T for w, part in zip(vector_blocks, vectors, strict=True))  # [B, out]
    if conv.bias is not None:
        shift = shift + conv.bias
    return y + shift.unsqueeze(-1)


def unit(x: Tensor, dim: int = -1, eps: float = 1e-12) -> Tensor:
    """L2-normalise along ``dim`` as ``x / sqrt(|x|² + eps²)``: equal to ``F.normalize`` up to rounding
    for non-zero x, but smooth at x = 0 (zero queries occur at every episode start, and the inner
    loop's second-order gradients through ``F.normalize``'s norm are NaN there)."""
    return x * torch.rsqrt(x.pow(2).sum(dim=dim, keepdim=True) + eps * eps)


def target_similarity(target_embedding: Tensor, category_glove: Tensor) -> Tensor:
    """CS column: cosine between the target's GloVe ``[B, D]`` and every category's ``[C, D]`` -> ``[B, C]``."""
    return unit(target_embedding) @ unit(category_glove).T


def target_row(context: Tensor, target_index: Tensor) -> Tensor:
    """The target category's context row ``[B, 4]`` (zeros where ``target_index`` is -1)."""
    index = target_index.clamp(min=0).view(-1, 1, 1).expand(-1, 1, context.shape[-1])
    row = context.gather(1, index).squeeze(1)
    return row * (target_index >= 0).to(row.dtype).unsqueeze(-1)


def target_context_input(obs: dict[str, Tensor], layer: nn.Module) -> Tensor:
    """``model.target_context``'s term of a target descriptor: ``layer`` (4 -> the descriptor's width)
    of the target category's own context row, added to the descriptor's GloVe term before its
    activation (docs/model.md, "Target context")."""
    row = target_row(obs["context"], obs["target_index"])
    return layer(row.unsqueeze(-1)).squeeze(-1) if isinstance(layer, nn.Conv1d) else layer(row)


def context_vector(obs: dict[str, Tensor], category_glove: Tensor) -> Tensor:
    """The paper's context vector per category, ``[B, C, 5] = [B_inview, x_c, y_c, A_bbox, CS]``.

    The first four columns come from the observation; CS is computed here for *every* category, in
    view or not (as MJOLNIR fills its fifth column)."""
    cs = target_similarity(obs["target_embedding"], category_glove)
    return torch.cat([obs["context"], cs.unsqueeze(-1)], dim=-1)


def normalized_adjacency_parameter(adjacency) -> nn.Parameter:
    """The references store the normalised adjacency itself as a trainable parameter."""
    from mapless.knowledge import normalize_adjacency

    return nn.Parameter(torch.as_tensor(normalize_adjacency(adjacency)))


# -- SAVN initialisation -------------------------------------------------------------------------
def glorot_init(module: nn.Module) -> None:
    """SAVN's ``weights_init``: uniform(±sqrt(6 / (fan_in + fan_out))) for every Conv/Linear weight,
    fan counts including the kernel, biases 0. Applied before the learned-loss modules exist, which
    (as in SAVN) keep PyTorch's default init."""
    for m in module.modules():
        if isinstance(m, nn.Conv1d | nn.Conv2d | nn.Linear):
            receptive = math.prod(m.weight.shape[2:]) if m.weight.dim() > 2 else 1
            fan_in, fan_out = m.weight.shape[1] * receptive, m.weight.shape[0] * receptive
            bound = math.sqrt(6.0 / (fan_in + fan_out))
            with torch.no_grad():
                m.weight.uniform_(-bound, bound)
                if m.bias is not None:
                    m.bias.zero_()


def normalized_column_init(linear: nn.Linear, std: float) -> None:
    """Rows of Gaussian weights rescaled to norm ``std`` (SAVN's actor 0.01 / critic 1.0), bias 0."""
    with torch.no_grad():
        w = torch.randn_like(linear.weight)
        linear.weight.copy_(w * std / w.pow(2).sum(dim=1, keepdim=True).sqrt())
        if linear.bias is not None:
            linear.bias.zero_()


def init_heads_and_lstm(model: nn.Module) -> None:
    """The rest of SAVN's init: actor std 0.01, critic std 1.0, LSTM biases 0 (weights keep PyTorch's)."""
    normalized_column_init(model.actor_linear, 0.01)
    normalized_column_init(model.critic_linear, 1.0)
    with torch.no_grad():
        model.lstm.bias_ih.zero_()
        model.lstm.bias_hh.zero_()
