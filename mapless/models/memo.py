"""Reuse of computations that see the observation only through the in-view indicator.

cvmeta's hierarchical GCN and MJOLNIR's object GCN take ``[in-view vector || node GloVe]`` as node
features, so their output is a function of which categories are in view, and an agent sees the same
set of categories again and again: it turns on the spot, steps back and forth, and starts episodes
in the same rooms. In a 32-episode training rollout of cvmeta about one row in three is new, and an
evaluation sees even fewer (docs/guide/training.md and docs/guide/evaluation.md give the measured shares and
speed-ups). While the GCN's
parameters stay fixed (one training rollout, one evaluation) an :class:`InViewMemo` sends each
distinct row through it once and hands out the stored result afterwards. Results keep their
autograd history, so the gradient of every step that used a stored row flows into the one
computation that produced it: the same gradient as without the memo, up to rounding.

The same holds for the terms those computations share across rows, which depend on the parameters
alone (the GCNs' first-layer term ``Â · F · W_Fᵀ`` of :func:`~mapless.models.layers.shared_row_gcn_layer`):
:meth:`InViewMemo.constant` computes each once while the memo is in use, where every step would
compute (and backpropagate) it again.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor


class InViewMemo:
    """``compute(rows)`` row by row, each distinct row computed once (``compute`` maps ``[N, C]``
    rows to ``[N, ...]`` results, row by row, with parameters that must not change while the memo
    is in use).

    Rows are matched on their exact bytes. ``max_rows`` bounds the memory: when a batch would
    take the store past it, the store starts afresh (evaluations run for hours of simulated time).
    A training rollout passes None: its steps' outputs hold every stored result's graph until the
    update anyway, so starting afresh would free nothing and only lose the reuse.
    """

    def __init__(self, max_rows: int | None = 2048):
        self.max_rows = max_rows
        self.computed_rows = 0  # rows sent through ``compute`` so far (for tests and benchmarks)
        self.requested_rows = 0
        self.computed_constants = 0
        self._chunks: list[Tensor] = []
        self._where: dict[bytes, tuple[int, int]] = {}  # row bytes -> (chunk, row in chunk)
        self._constants: dict[str, Tensor] = {}

    def __len__(self) -> int:
        return len(self._where)

    def __call__(self, rows: Tensor, compute: Callable[[Tensor], Tensor]) -> Tensor:
        keys = [row.tobytes() for row in rows.detach().cpu().numpy()]
        fresh = list(dict.fromkeys(k for k in keys if k not in self._where))
        if self.max_rows is not None and len(self._where) + len(fresh) > self.max_rows:
            self._chunks, self._where = [], {}
            fresh = list(dict.fromkeys(keys))
        if fresh:
            first = {k: i for i, k in reversed(list(enumerate(keys)))}
            chunk = len(self._chunks)
            positions = torch.tensor([first[k] for k in fresh], device=rows.device)
            self._chunks.append(compute(rows.index_select(0, positions)))
            self._where.update((k, (chunk, i)) for i, k in enumerate(fresh))
            self.computed_rows += len(fresh)
        self.requested_rows += len(keys)
        return self._gather([self._where[k] for k in keys], rows.device)

    def constant(self, key: str, compute: Callable[[], Tensor]) -> Tensor:
        """``compute()`` of a parameter-only term, computed on the first call with ``key`` and handed
        out afterwards (starting the row store afresh keeps it: the parameters have not changed)."""
        if key not in self._constants:
            self._constants[key] = compute()
            self.computed_constants += 1
        return self._constants[key]

    def _gather(self, where: list[tuple[int, int]], device: torch.device) -> Tensor:
        """Stored rows in request order: one ``index_select`` per chunk, then one reordering."""
        by_chunk: dict[int, list[int]] = {}
        for position, (chunk, _) in enumerate(where):
            by_chunk.setdefault(chunk, []).append(position)
        if len(by_chunk) == 1:
            (chunk,) = by_chunk
            index = torch.tensor([row for _, row in where], device=device)
            return self._chunks[chunk].index_select(0, index)
        parts, order = [], []
        for chunk, positions in by_chunk.items():
            index = torch.tensor([where[p][1] for p in positions], device=device)
            parts.append(self._chunks[chunk].index_select(0, index))
            order += positions
        inverse = torch.empty(len(order), dtype=torch.long)
        inverse[torch.tensor(order)] = torch.arange(len(order))
        return torch.cat(parts).index_select(0, inverse.to(device))
