"""The batched trainer computes, episode by episode, what the async (per-episode) trainer computes.

Both rollouts play the same episodes with the same per-episode action noise through the same loop:
the batched one with one forward per step for all episodes (and the vmapped inner loop for adaptive
models), the per-episode one at batch size 1. Their per-episode A3C losses,
per-episode gradients and the batch's mean gradient must agree (float32 round-off aside).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from train_fixtures import fixture_library, tiny_config

from mapless.agent.acting import observation_keys
from mapless.models.registry import model_class
from mapless.sim.vector import BatchedNavEnv
from mapless.train.builders import new_model, reward_config, target_fields, training_sampler
from mapless.train.gradients import trainable
from mapless.train.rollout import (
    accumulate_gradients,
    episode_losses,
    make_actor,
    run_batch,
)

B = 3
CPU = torch.device("cpu")


def _setup(name: str, *overrides: str):
    # The inner loop's settings for the models that have one: any other model refuses them.
    inner = ("model.interaction_steps=3", "model.max_inner_updates=2", "model.inner_lr=0.05")
    config = tiny_config(
        name, "env.max_steps=7", *(inner if model_class(name).is_adaptive() else ()), *overrides
    )
    torch.manual_seed(0)
    model = new_model(config)
    library = fixture_library()
    sampler = training_sampler(config, library, seed=3)
    rng = np.random.default_rng(5)
    episodes = [sampler.sample(rng) for _ in range(B)]
    # Scaled so that Done (the last 1/6 of the CDF at the start) is rare: long episodes, inner steps.
    noise = rng.random((B, config.env.max_steps)) * 0.9
    return config, model, library, episodes, noise


def _grads(model) -> list[torch.Tensor]:
    return [p.grad.clone() if p.grad is not None else torch.zeros_like(p) for p in trainable(model)]


@pytest.mark.parametrize(
    ("name", "first_order"),
    [("a3c", False), ("savn", False), ("cvmeta", True)],
)
def test_batched_losses_and_gradients_match_per_episode(name: str, first_order: bool) -> None:
    config, model, library, episodes, noise = _setup(name, f"meta.first_order={first_order}")
    keys = observation_keys(model)
    targets, rewards = target_fields(config), reward_config(config)

    # Per episode, as an async worker computes it (batch size 1).
    single_env = BatchedNavEnv(
        library, config.env.scene_list(), 1, targets=targets, rewards=rewards, max_steps=config.env.max_steps
    )
    single_losses, single_grads, lengths = [], [], []
    for b, episode in enumerate(episodes):
        actor = make_actor(model, first_order)
        model.zero_grad(set_to_none=True)
        trajectory = run_batch(actor, single_env, [episode], noise[b : b + 1], keys, CPU)
        single_losses.append(accumulate_gradients(actor, trajectory, config.a3c).total.detach()[0])
        single_grads.append(_grads(model))
        lengths.append(int(trajectory.length[0]))

    # All episodes in lockstep.
    batch_env = BatchedNavEnv(
        library, config.env.scene_list(), B, targets=targets, rewards=rewards, max_steps=config.env.max_steps
    )
    actor = make_actor(model, first_order)
    model.zero_grad(set_to_none=True)
    trajectory = run_batch(actor, batch_env, episodes, noise, keys, CPU)
    assert trajectory.length.tolist() == lengths
    if model.adaptive:
        assert actor.state.updates > 0, "the test episodes should be long enough for inner steps"
        theta0 = dict(model.named_parameters())
        assert any(not torch.equal(w, theta0[n].expand_as(w)) for n, w in actor.state.fast.items()), (
            "the inner steps should have moved the fast weights"
        )
    losses = episode_losses(trajectory, config.a3c)
    torch.testing.assert_close(losses.total.detach(), torch.stack(single_losses), rtol=1e-4, atol=1e-5)

    if not first_order:  # per-episode gradients straight from the batched graph
        for b in range(B):
            grads = actor.gradients(losses.total[b], trainable(model), retain_graph=True)
            for g, expected in zip(grads, single_grads[b], strict=True):
                g = torch.zeros_like(expected) if g is None else g
                torch.testing.assert_close(g, expected, rtol=1e-3, atol=1e-6)

    # The update the batched trainer applies: the mean of the per-episode gradients.
    actor.backward(losses.total.mean())
    for got, *per_episode in zip(_grads(model), *single_grads, strict=True):
        torch.testing.assert_close(got, torch.stack(per_episode).mean(0), rtol=1e-3, atol=1e-6)


@pytest.mark.parametrize("name", ["a3c", "sp", "savn", "cvmeta"])
def test_bf16_precision_gives_nearly_the_float32_gradient(name: str) -> None:
    """``a3c.precision: bf16`` (bfloat16 encoders and LSTM products) plays the same episodes and its
    batch gradient points where float32's does, up to bfloat16 rounding."""
    config, model, library, episodes, noise = _setup(name)
    keys = observation_keys(model)
    env = BatchedNavEnv(
        library,
        config.env.scene_list(),
        B,
        targets=target_fields(config),
        rewards=reward_config(config),
        max_steps=config.env.max_steps,
    )
    runs = {}
    for precision in ("fp32", "bf16"):
        actor = make_actor(model, precision=precision)
        model.zero_grad(set_to_none=True)
        trajectory = run_batch(actor, env, episodes, noise, keys, CPU)
        if name in ("cvmeta", "sp"):  # their GCN ran once per distinct in-view row of the rollout
            assert 0 < actor.memo.computed_rows < actor.memo.requested_rows
            assert actor.memo.requested_rows >= trajectory.frames
        else:
            assert actor.memo.requested_rows == 0
        losses = accumulate_gradients(actor, trajectory, config.a3c)
        runs[precision] = (trajectory, losses.total.detach(), torch.cat([g.flatten() for g in _grads(model)]))
    (exact, exact_loss, exact_grad), (low, low_loss, low_grad) = runs["fp32"], runs["bf16"]
    assert torch.equal(low.actions, exact.actions)
    torch.testing.assert_close(low_loss, exact_loss, rtol=0.02, atol=0.02)
    assert not torch.equal(low_grad, exact_grad)
    assert torch.nn.functional.cosine_similarity(low_grad, exact_grad, dim=0) > 0.99
