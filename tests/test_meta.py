"""The batched functional inner loop against a hand-unrolled per-episode autograd computation."""

import pytest
import torch
from torch.func import functional_call

from mapless.agent.meta import InnerLoop, TestTimeAdaptation
from mapless.knowledge import synthetic_knowledge
from mapless.models import build_model
from mapless.models.synthetic import synthetic_observations
from mapless.train.a3c_loss import a3c_loss

K = 3  # interaction steps per inner update in these tests
LR = 0.05  # large enough that adaptation visibly changes the outputs


def make_model(name: str = "savn", max_updates: int = 2, inner_lr: float = LR):
    torch.manual_seed(0)
    knowledge = synthetic_knowledge(5, 300, seed=1)
    model = (
        build_model(
            name,
            knowledge=knowledge,
            hidden_size=16,
            interaction_steps=K,
            max_inner_updates=max_updates,
            inner_lr=inner_lr,
        )
        .double()
        .eval()
    )
    return model, knowledge


def make_episodes(knowledge, T: int, B: int = 2, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    obs = []
    for _ in range(T):
        o = synthetic_observations(B, knowledge, generator=gen)
        obs.append({k: (v.double() if v.is_floating_point() else v) for k, v in o.items()})
    actions = torch.randint(0, 6, (T, B), generator=gen)
    rewards = torch.randn(T, B, generator=gen, dtype=torch.float64)
    return obs, actions, rewards


def batched_run(model, loop, obs, actions, rewards, lengths):
    T, B = actions.shape
    mask = torch.stack([torch.arange(T) < n for n in lengths], dim=1).double()
    state = loop.start(B)
    hidden = tuple(x.double() for x in model.initial_state(B))
    policy = torch.zeros(B, 6, dtype=torch.float64)
    logits, values = [], []
    for t in range(T):
        out = loop.forward(state, obs[t], hidden, policy)
        logits.append(out.logits)
        values.append(out.value)
        hidden, policy = out.hidden, torch.softmax(out.logits, -1)
        alive = torch.tensor([t < n - 1 for n in lengths])  # False on an episode's last step
        loop.observe(state, out, alive)
    loss = a3c_loss(torch.stack(logits), torch.stack(values), actions, rewards, mask).total.sum()
    return state, torch.stack(logits), loss


def hand_run(model, obs, actions, rewards, lengths, max_updates, create_graph=True):
    """Per episode, plain autograd: θ as a dict, SAVN's name rule, one grad call per inner step."""
    theta0 = {n: p for n, p in model.named_parameters() if p.requires_grad}
    names = model.inner_parameter_names()  # cvmeta: the policy network only (tests/test_models.py)
    total, all_logits, records = 0.0, [], []
    for b, n in enumerate(lengths):
        theta = {name: theta0[name] for name in names}
        hidden = tuple(x.double() for x in model.initial_state(1))
        policy = torch.zeros(1, 6, dtype=torch.float64)
        rows, updates, logits, values = [], 0, [], []
        for t in range(n):
            single = {k: v[b : b + 1] for k, v in obs[t].items()}
            out = functional_call(model, theta, (single, hidden, policy))
            logits.append(out.logits)
            values.append(out.value)
            hidden, policy = out.hidden, torch.softmax(out.logits, -1)
            rows.append(torch.cat([hidden[0], policy], -1))
            if len(rows) == K:
                if updates < max_updates and t < n - 1:
                    loss = model.learned_loss(torch.stack(rows, 1))[0]
                    grads = torch.autograd.grad(
                        loss, [theta[m] for m in names], create_graph=create_graph, allow_unused=True
                    )
                    g = dict(zip(names, grads, strict=True))
                    theta = {m: theta[m] if g[m] is None else theta[m] - LR * g[m] for m in names}
                    records.append((b, g, theta))
                    updates += 1
                rows = []
        all_logits.append(torch.cat(logits))
        total = (
            total
            + a3c_loss(
                torch.stack(logits),
                torch.stack(values),
                actions[:n, b : b + 1],
                rewards[:n, b : b + 1],
                torch.ones(n, 1, dtype=torch.float64),
            ).total.sum()
        )
    return total, all_logits, records


def grads_of(model):
    return {
        n: (p.grad.clone() if p.grad is not None else torch.zeros_like(p))
        for n, p in model.named_parameters()
    }


@pytest.mark.parametrize("name", ["savn", "cvmeta"])
def test_inner_loop_equals_hand_unrolled_second_order(name):
    model, knowledge = make_model(name)
    lengths = [7, 4]  # episode 1 ends at step 4: no second update for it
    obs, actions, rewards = make_episodes(knowledge, 7)
    loop = InnerLoop(model)
    state, logits, loss = batched_run(model, loop, obs, actions, rewards, lengths)
    assert state.updates == 2
    loop.backward(state, loss)
    batched = grads_of(model)
    model.zero_grad(set_to_none=True)
    hand_loss, hand_logits, records = hand_run(model, obs, actions, rewards, lengths, 2)
    assert [r[0] for r in records] == [0, 0, 1]
    hand_loss.backward()
    hand = grads_of(model)
    assert loss.item() == pytest.approx(hand_loss.item(), rel=1e-10)
    for b, n in enumerate(lengths):
        assert torch.allclose(logits[:n, b], hand_logits[b], atol=1e-10)
    for n in batched:
        assert torch.allclose(batched[n], hand[n], atol=1e-12, rtol=1e-9), n
    # Adaptation really changed the policy: without inner steps the logits agree only before step k.
    _, plain, _ = batched_run(model, InnerLoop(model, max_updates=0), obs, actions, rewards, lengths)
    assert torch.allclose(plain[:K], logits[:K], atol=1e-12)
    assert not torch.allclose(plain[K:, 0], logits[K:, 0], atol=1e-6)
    phi = model.learned_loss_parameter_names()
    assert all(batched[n].abs().sum() > 0 for n in phi)


def test_phi_gets_gradient_only_through_the_inner_step():
    model, knowledge = make_model()
    obs, actions, rewards = make_episodes(knowledge, K - 1)  # shorter than k: no inner step at all
    loop = InnerLoop(model)
    state, _, loss = batched_run(model, loop, obs, actions, rewards, [K - 1, K - 1])
    loop.backward(state, loss)
    assert all(p.grad is None for n, p in model.named_parameters() if n.startswith("ll_"))
    assert model.lstm.weight_ih.grad.abs().sum() > 0

    # With α = 0 the inner step is the identity and φ's meta-gradient vanishes exactly.
    model, knowledge = make_model(inner_lr=0.0)
    obs, actions, rewards = make_episodes(knowledge, 5)
    loop = InnerLoop(model)
    state, _, loss = batched_run(model, loop, obs, actions, rewards, [5, 5])
    loop.backward(state, loss)
    assert all(p.grad.abs().max() == 0 for n, p in model.named_parameters() if n.startswith("ll_"))


def test_first_order_differs_from_second_order_by_the_hessian_term():
    lengths = [5, 5]  # one inner step (after step 3), then two adapted steps
    model, knowledge = make_model(max_updates=1)
    obs, actions, rewards = make_episodes(knowledge, 5, seed=3)
    loop = InnerLoop(model)
    state, _, loss = batched_run(model, loop, obs, actions, rewards, lengths)
    loop.backward(state, loss)
    second = grads_of(model)
    model.zero_grad(set_to_none=True)
    loop = InnerLoop(model, first_order=True)
    state, _, loss_fo = batched_run(model, loop, obs, actions, rewards, lengths)
    loop.backward(state, loss_fo)
    first = grads_of(model)
    model.zero_grad(set_to_none=True)
    assert loss_fo.item() == pytest.approx(loss.item(), rel=1e-12)  # same trajectory and outer loss

    # Hand: v = ∂L/∂θ_1, term = (∂g/∂θ_0)ᵀ v (the interaction loss's Hessian-vector product).
    hand_loss, _, records = hand_run(model, obs, actions, rewards, lengths, 1)
    theta0 = dict(model.named_parameters())
    term = {n: torch.zeros_like(p) for n, p in theta0.items()}
    for _, g, theta1 in records:
        used = [m for m in g if g[m] is not None]
        v = torch.autograd.grad(hand_loss, [theta1[m] for m in used], retain_graph=True)
        inner = sum((g[m] * vm.detach()).sum() for m, vm in zip(used, v, strict=True))
        names = [n for n in theta0 if not n.startswith("ll_")]
        hvp = torch.autograd.grad(inner, [theta0[n] for n in names], retain_graph=True, allow_unused=True)
        for n, h in zip(names, hvp, strict=True):
            if h is not None:
                term[n] += h
    for n in second:
        if n.startswith("ll_"):
            assert torch.allclose(first[n], second[n], atol=1e-10), n  # φ: identical for one step
            assert second[n].abs().sum() > 0
        else:
            assert torch.allclose(second[n] - first[n], -LR * term[n], atol=1e-9, rtol=1e-6), n
    assert sum(term[n].abs().sum() for n in term) > 0


def test_test_time_adaptation_keeps_no_graph_and_matches_training_outputs():
    model, knowledge = make_model()
    obs, actions, rewards = make_episodes(knowledge, 7, seed=5)
    _, train_logits, _ = batched_run(model, InnerLoop(model), obs, actions, rewards, [7, 7])
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    loop = TestTimeAdaptation(model)
    state, eval_logits, _ = batched_run(model, loop, obs, actions, rewards, [7, 7])
    assert state.slot_updates.tolist() == [2, 2]
    assert torch.allclose(eval_logits, train_logits, atol=1e-10)
    assert all(w.grad_fn is None for w in state.fast.values())
    assert state.left.grad_fn is None and len(state.chunk) == 1  # step 7 only: chunks never pile up
    assert all(torch.equal(before[n], p) for n, p in model.named_parameters())
    assert not hasattr(loop, "backward")  # no meta-gradient at test time


def test_update_limit_and_no_update_after_episode_end():
    model, knowledge = make_model(max_updates=1)
    obs, actions, rewards = make_episodes(knowledge, 7)
    state, _, _ = batched_run(model, InnerLoop(model), obs, actions, rewards, [7, 7])
    assert state.updates == 1
    model, knowledge = make_model()
    state, _, _ = batched_run(model, InnerLoop(model), obs, actions, rewards, [K, K])  # both end at step k
    assert state.updates == 0


def test_non_adaptive_models_are_rejected():
    model, _ = make_model()
    a3c = build_model("a3c", knowledge=synthetic_knowledge(5), hidden_size=16)
    assert model.adaptive and not a3c.adaptive
    with pytest.raises(TypeError):
        InnerLoop(a3c)


def compacted_run(model, loop, obs, actions, rewards, lengths):
    """``batched_run``, but ended episodes are dropped from the batch after the step that ends them
    (as the trainer's rollout does), mid-chunk included; outputs are scattered back to the full
    batch."""
    T, B = actions.shape
    mask = torch.stack([torch.arange(T) < n for n in lengths], dim=1).double()
    state = loop.start(B)
    hidden = tuple(x.double() for x in model.initial_state(B))
    policy = torch.zeros(B, 6, dtype=torch.float64)
    slots = torch.arange(B)
    logits, values = [], []
    for t in range(T):
        out = loop.forward(state, {k: v[slots] for k, v in obs[t].items()}, hidden, policy)
        logits.append(out.logits.new_zeros(B, 6).index_copy(0, slots, out.logits))
        values.append(out.value.new_zeros(B, 1).index_copy(0, slots, out.value))
        hidden, policy = out.hidden, torch.softmax(out.logits, -1)
        alive = torch.tensor([t < lengths[b] - 1 for b in slots.tolist()])
        loop.observe(state, out, alive)
        if not alive.all() and alive.any():
            keep = torch.nonzero(alive).squeeze(1)
            loop.compact(state, keep)
            slots = slots[keep]
            hidden = tuple(x.index_select(0, keep) for x in hidden)
            policy = policy.index_select(0, keep)
    loss = a3c_loss(torch.stack(logits), torch.stack(values), actions, rewards, mask).total.sum()
    return state, loss


@pytest.mark.parametrize("first_order", [False, True])
@pytest.mark.parametrize("name", ["cvmeta", "savn"])
def test_dropping_ended_episodes_changes_nothing(name, first_order):
    model, knowledge = make_model(name, max_updates=3)
    obs, actions, rewards = make_episodes(knowledge, 12, B=4, seed=7)
    # Chunks of K = 3 steps: episode 1 leaves within the first chunk (while every episode still
    # reads θ_0), episodes 2 and 3 within the second and third, after inner steps.
    lengths = [12, 2, 5, 8]
    results = []
    for run in (batched_run, compacted_run):
        model.zero_grad(set_to_none=True)
        loop = InnerLoop(model, first_order=first_order)
        state, *_, loss = run(model, loop, obs, actions, rewards, lengths)
        assert state.updates == 3
        loop.backward(state, loss)
        results.append((loss.item(), grads_of(model)))
    (full_loss, full), (compact_loss, compact) = results
    assert compact_loss == pytest.approx(full_loss, rel=1e-12)
    for n in full:
        assert torch.allclose(compact[n], full[n], atol=1e-10, rtol=1e-8), n


def per_step_replay(loop, obs, prev_policy, mask, columns):
    """The adaptive replay as the PPO trainer wrote it before :meth:`InnerLoop.replay`: the slots
    ``columns`` of a recorded segment (``mask [T, N]`` float) stepped one at a time, each step
    selecting its running episodes' rows out of the whole segment."""
    mask = mask[:, columns]
    steps, batch = int(mask.sum(0).max()), len(columns)
    state = loop.start(batch)
    hidden = tuple(h.double() for h in loop.model.initial_state(batch))
    rows = torch.arange(batch)
    logits, values = [], []
    for t in range(steps):
        episodes = columns.index_select(0, rows)
        step_obs = {k: v[t].index_select(0, episodes) for k, v in obs.items()}
        out = loop.forward(state, step_obs, hidden, prev_policy[t].index_select(0, episodes))
        alive = (
            (mask[t + 1].index_select(0, rows) > 0) if t + 1 < len(mask) else mask.new_zeros(len(rows)).bool()
        )
        loop.observe(state, out, alive)
        logits.append(out.logits.new_zeros(batch, out.logits.shape[-1]).index_copy(0, rows, out.logits))
        values.append(out.value.new_zeros(batch).index_copy(0, rows, out.value.reshape(-1)))
        hidden = out.hidden
        if t + 1 < steps and not bool(alive.all()):
            keep = alive.nonzero().squeeze(1)
            loop.compact(state, keep)
            rows = rows.index_select(0, keep)
            hidden = tuple(h.index_select(0, keep) for h in hidden)
    return torch.stack(logits), torch.stack(values), state


def recorded_segment(knowledge, lengths, steps=12, seed=3):
    """A segment of ``len(lengths)`` slots whose episodes take ``lengths`` steps from row 0: obs,
    prev_policy and the float mask; the rows after an episode's end are NaN (float inputs), so any
    read of them shows in the outputs or gradients."""
    slots = len(lengths)
    obs_list, _, _ = make_episodes(knowledge, steps, B=slots, seed=seed)
    obs = {k: torch.stack([o[k] for o in obs_list]) for k in obs_list[0]}
    gen = torch.Generator().manual_seed(seed + 1)
    prev_policy = torch.softmax(torch.randn(steps, slots, 6, generator=gen, dtype=torch.float64), -1)
    mask = torch.stack([torch.arange(steps) < n for n in lengths], dim=1).double()
    padding = mask == 0
    for value in (*obs.values(), prev_policy):
        if value.is_floating_point():
            value[padding] = float("nan")
    return obs, prev_policy, mask


@pytest.mark.parametrize("max_updates", [3, 1])
@pytest.mark.parametrize("first_order", [False, True])
@pytest.mark.parametrize("name", ["cvmeta", "savn", "gve", "spatt"])
def test_replay_of_whole_episodes_equals_the_per_step_replay(name, first_order, max_updates):
    """:meth:`InnerLoop.replay` of a minibatch of a recorded segment (its columns taken first) gives
    the outputs and meta-gradient of the per-step replay, in float64 to 1e-9: the chunks encoded
    at once (cvmeta, savn; gve's critic input too), and spatt's step-by-step encoder; with
    ``max_updates = 1`` the last chunk runs from the first inner step to the end."""
    model, knowledge = make_model(name, max_updates=max_updates)
    steps = 12
    # Episodes end inside a chunk (before and after an inner step), at a chunk's end, on their
    # first step, and the longest one is shorter than the segment (its last rows are padding).
    lengths = [9, 2, 6, 1, 4]
    obs, prev_policy, mask = recorded_segment(knowledge, lengths, steps)
    columns = torch.tensor([4, 0, 2, 1])  # a minibatch: a permuted subset of the slots
    gen = torch.Generator().manual_seed(5)
    weights = torch.randn(steps, len(columns), 6, generator=gen, dtype=torch.float64)
    results = []
    for new in (True, False):
        model.zero_grad(set_to_none=True)
        loop = InnerLoop(model, first_order=first_order)
        if new:
            selected = {k: v[:, columns] for k, v in obs.items()}
            logits, values, state = loop.replay(selected, prev_policy[:, columns], mask[:, columns] > 0)
        else:
            logits, values, state = per_step_replay(loop, obs, prev_policy, mask, columns)
        # the longest episode (9 steps, k = 3) adapts after steps 3 and 6, up to the limit
        assert state.updates == min(2, max_updates)
        objective = ((logits * weights[: len(logits)]).sum(-1) + values) * mask[: len(logits), columns]
        loop.backward(state, objective.nan_to_num().sum())  # NaN padding outputs are masked out
        results.append((logits.detach(), values.detach(), grads_of(model)))
    (logits, values, grads), (ref_logits, ref_values, ref_grads) = results
    assert logits.shape == (9, 4, 6)
    acted = mask[:9, columns] > 0
    assert torch.isfinite(logits[acted]).all() and torch.isfinite(values[acted]).all()
    torch.testing.assert_close(logits[acted], ref_logits[acted], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(values[acted], ref_values[acted], rtol=1e-9, atol=1e-9)
    assert grads.keys() == ref_grads.keys() and any(g.abs().sum() > 0 for g in grads.values())
    for n in grads:
        assert torch.isfinite(grads[n]).all(), n
        torch.testing.assert_close(grads[n], ref_grads[n], rtol=1e-9, atol=1e-9, msg=n)


@pytest.mark.parametrize(
    ("name", "max_updates", "chunks"),
    [("savn", 3, 3), ("cvmeta", 1, 2), ("cvmeta", 0, 1), ("spatt", 3, 0)],
)
def test_replay_multiplies_each_chunk_by_weight_ih_once(name, max_updates, chunks):
    """Where the encoder does not read h, a chunk (the steps between inner steps; the rest of the
    episodes after the last) takes one product with ``weight_ih`` and a step one with ``weight_hh``
    alone; spatt's encoder reads h, so each of its steps takes one product with both."""
    model, knowledge = make_model(name, max_updates=max_updates)
    lengths = [9, 2, 6, 1, 4]
    obs, prev_policy, mask = recorded_segment(knowledge, lengths)
    loop = InnerLoop(model)
    logits, _, state = loop.replay(obs, prev_policy, mask > 0)
    forward = [(len(rows), part) for rows, _, transpose, part in state.lstm.records if not transpose]
    per_step = [part for _, part in forward if part != "weight_ih"]
    assert per_step == (["weight_hh"] if chunks else [None]) * len(logits)
    chunk_rows = [n for n, part in forward if part == "weight_ih"]
    assert len(chunk_rows) == chunks
    if chunks:  # every acted step's row once: the chunks' products cover the episodes exactly
        assert sum(chunk_rows) == sum(lengths)
