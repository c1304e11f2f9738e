"""The in-view memo: each distinct in-view row through the object GCN once, with the same outputs and
gradients as computing every row (mapless.models.memo)."""

import pytest
import torch

from mapless.knowledge import synthetic_knowledge
from mapless.models import build_model
from mapless.models.memo import InViewMemo
from mapless.models.synthetic import synthetic_observations


def test_memo_computes_each_distinct_row_once_and_returns_rows_in_request_order():
    calls = []

    def compute(rows):
        calls.append(rows.clone())
        return torch.stack([rows.sum(-1), rows[:, 0] * 10], dim=-1)

    memo = InViewMemo()
    a, b, c = torch.tensor([1.0, 0, 1]), torch.tensor([0.0, 1, 0]), torch.tensor([1.0, 1, 1])
    first = memo(torch.stack([a, b, a]), compute)
    second = memo(torch.stack([c, b, a, c]), compute)  # b and a come from the first chunk
    assert first.tolist() == [[2, 10], [1, 0], [2, 10]]
    assert second.tolist() == [[3, 10], [1, 0], [2, 10], [3, 10]]
    assert [len(rows) for rows in calls] == [2, 1]  # a, b; then only c
    assert (memo.computed_rows, memo.requested_rows, len(memo)) == (3, 7, 3)


def test_memo_starts_afresh_past_max_rows():
    memo = InViewMemo(max_rows=2)
    rows = torch.eye(3)
    memo(rows[:2], lambda r: r * 2)
    out = memo(rows[1:], lambda r: r * 2)  # would hold 3 rows: the store restarts with this batch
    assert torch.equal(out, rows[1:] * 2)
    assert len(memo) == 2 and memo.computed_rows == 4


def test_unbounded_memo_never_starts_afresh():
    memo = InViewMemo(max_rows=None)
    rows = torch.eye(5000)
    memo(rows[:3000], lambda r: r * 2)
    out = memo(rows[2000:], lambda r: r * 2)
    assert torch.equal(out, rows[2000:] * 2)
    assert len(memo) == 5000 and memo.computed_rows == 5000


def test_memo_computes_a_constant_once_and_keeps_it_when_the_rows_start_afresh():
    memo, calls = InViewMemo(max_rows=1), []

    def term():
        calls.append(1)
        return torch.ones(2)

    first = memo.constant("term", term)
    memo(torch.eye(2), lambda r: r * 2)  # two rows past max_rows = 1: the row store restarts
    assert memo.constant("term", term) is first and len(calls) == 1
    assert memo.constant("other", lambda: torch.zeros(1)).shape == (1,) and memo.computed_constants == 2


@pytest.mark.parametrize("name", ["cvmeta", "mjolnir_o", "sp", "gve"])
def test_memoized_rollout_has_the_same_outputs_and_gradients(name):
    """Five steps of four episodes drawn from four observations with three distinct in-view rows
    (0 and 3 see the same categories in other boxes): the loss and every parameter gradient match
    the unmemoized computation, while the GCN sees only three rows."""
    torch.manual_seed(0)
    knowledge = synthetic_knowledge(6, 300, seed=0)
    model = build_model(name, knowledge=knowledge, hidden_size=24).eval()  # dropout off
    pool = synthetic_observations(4, knowledge, generator=torch.Generator().manual_seed(1))
    in_view = torch.tensor([[1.0, 0, 1, 0, 0, 1], [0, 1, 0, 0, 1, 0], [0, 0, 0, 0, 0, 0], [1, 0, 1, 0, 0, 1]])
    pool["context"] = torch.cat([in_view[..., None], torch.rand(4, 6, 3)], -1) * in_view[..., None]
    picks = torch.tensor([[0, 1, 2, 3], [1, 1, 0, 2], [2, 3, 0, 1], [0, 2, 1, 1], [2, 2, 2, 3]])
    weights = torch.randn(len(picks), 4, 6)

    def rollout_loss():
        hidden, prev = model.initial_state(4), torch.zeros(4, 6)
        loss = 0.0
        for step, pick in enumerate(picks):
            out = model({k: v[pick] for k, v in pool.items()}, hidden, prev)
            loss = loss + (out.logits * weights[step]).sum() + out.value.square().sum()
            hidden, prev = out.hidden, torch.softmax(out.logits, -1)
        return loss

    params = [p for n, p in model.named_parameters() if not n.startswith("ll_")]  # not in forward
    plain = rollout_loss()
    plain_grads = torch.autograd.grad(plain, params)
    with model.memoizing_in_view() as memo:
        memoized = rollout_loss()
    memo_grads = torch.autograd.grad(memoized, params)
    assert memo.computed_rows == 3 and memo.requested_rows == 20
    assert memo.computed_constants == 1  # the GCN's first-layer shared term, once for five steps
    torch.testing.assert_close(memoized, plain)
    for got, want in zip(memo_grads, plain_grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    assert model._in_view_memo is None  # the block restores the model


def test_models_whose_encoders_adapt_per_episode_do_not_memoize():
    knowledge = synthetic_knowledge(6, 300, seed=0)
    with build_model("cvmeta", knowledge=knowledge, adapt="policy").memoizing_in_view() as memo:
        assert isinstance(memo, InViewMemo)
    with build_model("cvmeta", knowledge=knowledge, adapt="all").memoizing_in_view() as memo:
        assert memo is None
