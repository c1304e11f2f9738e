"""Every model trains for a few hundred environment steps in a minimal A3C (+ inner loop) loop.

The toy task: synthetic observations, reward +1 for MoveAhead (action 0) and -0.01 otherwise, Done
(action 5) ends the episode. Every learned model must raise the probability of MoveAhead."""

import pytest
import torch

from mapless.agent.meta import InnerLoop, TestTimeAdaptation
from mapless.knowledge import synthetic_knowledge
from mapless.models import build_model, model_names
from mapless.models.synthetic import synthetic_observations
from mapless.train.a3c_loss import a3c_loss

BATCH, LENGTH, ROLLOUTS = 3, 8, 10  # 240 environment steps per model


def rollout(model, knowledge, gen, train: bool):
    loop = (InnerLoop(model) if train else TestTimeAdaptation(model)) if model.adaptive else None
    state = loop.start(BATCH) if loop else None
    hidden, policy = model.initial_state(BATCH), torch.zeros(BATCH, 6)
    alive = torch.ones(BATCH, dtype=torch.bool)
    logits, values, actions, rewards, masks = [], [], [], [], []
    for _ in range(LENGTH):
        obs = synthetic_observations(BATCH, knowledge, generator=gen)
        out = loop.forward(state, obs, hidden, policy) if loop else model(obs, hidden, policy)
        action = torch.multinomial(torch.softmax(out.logits.detach(), -1), 1, generator=gen).squeeze(1)
        masks.append(alive.float())
        rewards.append(torch.where(action == 0, 1.0, -0.01))
        alive = alive & (action != 5)
        logits.append(out.logits)
        values.append(out.value)
        actions.append(action)
        if loop:
            loop.observe(state, out, alive)
        hidden, policy = out.hidden, torch.softmax(out.logits, -1)
    bootstrap = torch.zeros(BATCH) if not alive.any() else values[-1].detach().squeeze(1) * alive
    loss = a3c_loss(
        torch.stack(logits),
        torch.stack(values),
        torch.stack(actions),
        torch.stack(rewards),
        torch.stack(masks),
        bootstrap,
    )
    return loop, state, loss, torch.softmax(torch.stack(logits), -1)[..., 0].mean().item()


@pytest.mark.parametrize("name", model_names())
def test_model_trains_a_few_hundred_steps(name):
    torch.manual_seed(0)
    knowledge = synthetic_knowledge(5, 300, seed=0)
    model = build_model(
        name, knowledge=knowledge, hidden_size=16, interaction_steps=3, max_inner_updates=2, inner_lr=0.01
    )
    gen = torch.Generator().manual_seed(0)
    params = [p for p in model.parameters() if p.requires_grad]
    before = [p.detach().clone() for p in params]
    optimizer = torch.optim.Adam(params, lr=2e-2) if params else None
    start, adapted = None, 0
    for _ in range(ROLLOUTS):
        loop, state, loss, p_move = rollout(model, knowledge, gen, train=True)
        start = p_move if start is None else start
        total = loss.total.mean()
        assert torch.isfinite(total)
        if optimizer is None:
            assert not total.requires_grad  # random: nothing to learn
            continue
        optimizer.zero_grad()
        if loop:
            loop.backward(state, total)
            adapted += state.updates
        else:
            total.backward()
        torch.nn.utils.clip_grad_norm_(params, 100.0)
        optimizer.step()
    if optimizer is None:
        assert start == pytest.approx(1 / 6)
        return
    assert any(not torch.equal(b, p) for b, p in zip(before, params, strict=True))
    assert adapted > 0 or not model.adaptive  # the inner loop ran inside training
    model.eval()
    with torch.no_grad() if not model.adaptive else torch.enable_grad():
        *_, after = rollout(model, knowledge, torch.Generator().manual_seed(1), train=False)
    assert after > start + 0.02, (start, after)
