"""The functional layers the models are built from: the LSTM step, GCN layers, pointwise
convolutions, tiling and the context-vector terms.

Every function works on plain tensors and the parameters of the module it is given, so the same
code runs under ``torch.func.functional_call`` and under ``vmap`` with per-episode weights (the
meta-learning inner loop, :mod:`mapless.agent.meta`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapless.knowledge import normalize_adjacency


def scatter_rows(t: Tensor, ids: Tensor, size: int) -> Tensor:
    """``t``'s rows placed at ``ids`` in a zero tensor of ``size`` rows (differentiable in ``t``)."""
    if len(ids) == size:
        return t
    return t.new_zeros(size, *t.shape[1:]).index_copy(0, ids, t)


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
    they stay fixed (:meth:`NavModel.fixed_term`). The outer product is a broadcast product and the
    shared term is added in place: the ``[C, B, out]`` result is written once, in the products' dtype
    (bfloat16 under autocast), and is a tensor of its own, not a view, so callers may apply their
    activation in place without autograd copying its base back in the backward pass.
    """
    per_episode = in_view @ layer.weight[:, : in_view.shape[-1]].T  # [B, out]
    out = adjacency.sum(-1).view(-1, 1, 1).to(per_episode.dtype) * per_episode.unsqueeze(0)
    out = out.add_(shared.unsqueeze(1).to(out.dtype))
    return out if layer.bias is None else out.add_(layer.bias.to(out.dtype))


def shared_gcn_term(adjacency: Tensor, node_features: Tensor, layer: nn.Linear) -> Tensor:
    """``Â · F · W_Fᵀ`` ``[C, out]``, the batch-independent term of :func:`shared_row_gcn_layer`
    (``F``: node features ``[C, D]``; ``W_F``: the last ``D`` columns of ``layer``, which read them)."""
    return (adjacency @ node_features) @ layer.weight[:, -node_features.shape[-1] :].T


def propagate(adjacency: Tensor, x: Tensor) -> Tensor:
    """``Â · X`` of node-major features ``[C, B, F]``: one matrix product with no transposes.

    The GCNs keep their activations node-major because both of their products are then plain
    matrix products (``Â`` on the left of ``[C, B·F]``, ``W`` on the right of ``[C·B, F]``); the
    batch-major layout made every ``Â ·`` a transpose copy and a batched product. The result is a
    view of the product: an activation in place on it would make autograd copy the whole product
    twice in the backward pass, so callers apply theirs out of place."""
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


def target_context_input(obs: dict[str, Tensor], layer: nn.Module, with_distance: bool = False) -> Tensor:
    """``model.target_context``'s term of a target descriptor: ``layer`` (4 -> the descriptor's width;
    5 ``with_distance``) of the target category's own context row, added to the descriptor's GloVe
    term before its activation (docs/guide/models.md, "Target context")."""
    context = observed_context(obs, with_distance)
    row = target_row(context, obs["target_index"])
    return layer(row.unsqueeze(-1)).squeeze(-1) if isinstance(layer, nn.Conv1d) else layer(row)


def observed_context(obs: dict[str, Tensor], with_distance: bool = False) -> Tensor:
    """``obs["context"]`` ``[B, C, 4]``, and ``with_distance`` its fifth column
    ``obs["context_distance"]`` (``model.context_distance``)."""
    if not with_distance:
        return obs["context"]
    return torch.cat([obs["context"], obs["context_distance"].unsqueeze(-1)], dim=-1)


def context_vector(obs: dict[str, Tensor], category_glove: Tensor, with_distance: bool = False) -> Tensor:
    """The paper's context vector per category, ``[B, C, 5] = [B_inview, x_c, y_c, A_bbox, CS]``
    (``with_distance``: ``[B, C, 6]``, the distance before CS).

    The first four columns come from the observation; CS is computed here for *every* category, in
    view or not (as MJOLNIR fills its fifth column)."""
    cs = target_similarity(obs["target_embedding"], category_glove)
    return torch.cat([observed_context(obs, with_distance), cs.unsqueeze(-1)], dim=-1)


def normalized_adjacency_parameter(adjacency) -> nn.Parameter:
    """The references store the normalised adjacency itself as a trainable parameter."""
    return nn.Parameter(torch.as_tensor(normalize_adjacency(adjacency)))
