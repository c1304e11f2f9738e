"""PPO (``algo: ppo``): GAE and the clipped objective against hand computations, the segment replay
against step-by-step forwards, the adaptive replay's meta-gradient against per-episode ones, and
exact resume of a PPO run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from train_fixtures import fixture_library, tiny_config

from mapless import checkpoint as ckpt
from mapless.config import ConfigError
from mapless.models import build_model
from mapless.train.ppo import PPOTrainer, gae, ppo_loss
from mapless.train.run import resume_config, train


def test_gae_with_a_termination_and_a_truncation_inside_one_segment() -> None:
    # One slot, 5 steps: episode A ends by Done at t=1, episode B is cut by the time limit at t=3
    # (V of the state it was cut in: 2.0), episode C goes on past the segment (V after it: 4.0).
    rewards = torch.tensor([[1.0], [5.0], [-0.5], [0.25], [1.0]])
    values = torch.tensor([[0.5], [1.0], [0.2], [0.3], [0.6]])
    terminated = torch.tensor([[False], [True], [False], [False], [False]])
    truncated = torch.tensor([[False], [False], [False], [True], [False]])
    bootstrap = torch.tensor([[0.0], [0.0], [0.0], [2.0], [0.0]])
    gamma, lam = 0.9, 0.5
    advantages, returns = gae(
        rewards, values, torch.tensor([4.0]), terminated, truncated, bootstrap, gamma, lam
    )
    # By hand, backwards. t=4: δ = 1 + 0.9*4.0 - 0.6 = 4.0, A = 4.0
    # t=3 (truncated): δ = 0.25 + 0.9*2.0 - 0.3 = 1.75; A = 1.75 (no carry over the end)
    # t=2: δ = -0.5 + 0.9*0.3 - 0.2 = -0.43; A = -0.43 + 0.45*1.75 = 0.3575
    # t=1 (terminated): δ = 5 - 1 = 4; A = 4
    # t=0: δ = 1 + 0.9*1.0 - 0.5 = 1.4; A = 1.4 + 0.45*4 = 3.2
    expected = torch.tensor([[3.2], [4.0], [0.3575], [1.75], [4.0]])
    assert torch.allclose(advantages, expected)
    assert torch.allclose(returns, expected + values)


def test_clipped_objective_and_its_gradient() -> None:
    # Two steps with the same old probability 0.5 of action 0 (two actions), advantages +1 and -1.
    # Step 0's new probability 0.8 (ratio 1.6 > 1.2, A > 0): clipped, no gradient.
    # Step 1's new probability 0.55 (ratio 1.1, inside): -A·r, gradient -A·r·∂log π = r·(1 - π).
    p = torch.tensor([0.8, 0.55])
    logits = torch.stack([torch.log(p), torch.log(1 - p)], dim=1).requires_grad_()
    values = torch.zeros(2, requires_grad=True)
    old = torch.log(torch.tensor([0.5, 0.5]))
    loss = ppo_loss(
        logits,
        values,
        torch.tensor([0, 0]),
        old,
        torch.zeros(2),
        torch.tensor([1.0, -1.0]),
        torch.tensor([1.0, 3.0]),
        torch.ones(2),
        clip=0.2,
        value_clip=0.0,
        value_coef=0.5,
        entropy_coef=0.0,
    )
    # policy: mean(max(-A r, -A clip(r))) = mean(-1.2, 1.1) = -0.05; value: 0.5 * mean(1, 9) = 2.5
    assert loss.policy.item() == pytest.approx(-0.05)
    assert loss.value.item() == pytest.approx(2.5)
    assert loss.total.item() == pytest.approx(-0.05 + 0.5 * 2.5)
    assert loss.clip_fraction.item() == pytest.approx(0.5)
    loss.policy.backward()
    # d(policy)/d logit_0 of step 1: ½ · r · ∂log π_0/∂logit_0 = ½ · 1.1 · (1 - 0.55)
    assert logits.grad[0].abs().max().item() == 0.0
    assert logits.grad[1, 0].item() == pytest.approx(0.5 * 1.1 * 0.45, rel=1e-5)
    assert values.grad is None


@pytest.mark.parametrize("name", ["a3c", "mjolnir_o", "mlp", "sp"])
def test_segment_replay_equals_stepping_the_model_with_resets(name: str) -> None:
    torch.manual_seed(0)
    model = build_model(name, hidden_size=16, dropout=0.0).eval()
    steps, batch, c = 5, 3, model.num_categories
    context = torch.rand(steps, batch, c, 4) * (torch.rand(steps, batch, c, 1) < 0.1)
    obs = {
        "context": context,
        "features": torch.rand(steps, batch, model.feature_channels, 7, 7),
        "target_embedding": torch.randn(steps, batch, model.glove_dim),
        "target_index": torch.randint(0, c, (steps, batch)),
    }
    prev_policy = torch.softmax(torch.randn(steps, batch, 6), -1)
    starts = torch.zeros(steps, batch, dtype=torch.bool)
    starts[2, 1] = starts[4, 0] = True  # new episodes inside the segment
    hidden = (torch.randn(batch, model.hidden_size), torch.randn(batch, model.hidden_size))
    logits, values = model.replay(obs, prev_policy, starts, hidden)
    h, c_ = hidden
    for t in range(steps):
        keep = (~starts[t]).float().unsqueeze(-1)
        out = model({k: v[t] for k, v in obs.items()}, (h * keep, c_ * keep), prev_policy[t])
        assert torch.allclose(out.logits, logits[t], atol=1e-5), t
        assert torch.allclose(out.value.squeeze(-1), values[t], atol=1e-5), t
        h, c_ = out.hidden
    # The state after a start does not depend on what came before it.
    other = (torch.randn_like(hidden[0]), torch.randn_like(hidden[1]))
    again, _ = model.replay(obs, prev_policy, starts, other)
    assert torch.allclose(again[4, 0], logits[4, 0], atol=1e-6)
    assert torch.allclose(again[3, 1], logits[3, 1], atol=1e-6)
    assert not torch.allclose(again[1, 2], logits[1, 2])


@pytest.mark.parametrize("model", ["a3c", "savn", "cvmeta"])
def test_replay_reproduces_the_acting_policy(model: str) -> None:
    """With the parameters that acted, every replayed log-probability is the recorded one (ratio 1):
    segments with episode starts inside them, and whole episodes through the inner loop. A large inner
    learning rate makes every difference in how acting and replay adapt visible (acting once cut the
    recurrence at every step where the inner loop cuts it at chunk starts: values then differed by
    1e-2)."""
    adapt = [] if model == "a3c" else ["model.inner_lr=0.1"]
    trainer = PPOTrainer(
        tiny_config(model, "algo=ppo", "ppo.envs=4", "ppo.steps=12", "frames=100", *adapt),
        None,
        fixture_library,
    )
    trainer.build()
    segment = trainer.collector.collect(12 if model == "a3c" else 8, trainer.rng)
    if model == "a3c":
        assert segment.starts[1:].any(), "the fixture's episodes should end inside the segment"
    if trainer.inner is None:
        logits, values = trainer.model.replay(
            segment.obs, segment.prev_policy, segment.starts, segment.hidden
        )
    else:
        logits, values, _ = trainer.inner.replay(segment.obs, segment.prev_policy, segment.mask > 0)
    steps = logits.shape[0]
    log_prob = torch.log_softmax(logits, -1).gather(-1, segment.actions[:steps, :, None]).squeeze(-1)
    mask = segment.mask[:steps] > 0
    assert torch.allclose(log_prob[mask], segment.log_prob[:steps][mask], atol=1e-5)
    assert torch.allclose(values[mask], segment.values[:steps][mask], atol=1e-5)


def test_a_whole_episode_cut_by_the_step_limit_bootstraps_with_its_next_steps_value() -> None:
    """With ``ppo.bootstrap_time_limit`` an adaptive episode truncated at step T is bootstrapped with
    the value its step T + 1 has when the limit is one step later (same seed: the same episodes and
    actions), under its adapted fast weights; without it the limit is an end (the references' R = 0)."""

    def collect(max_steps: int, *extra: str):
        config = tiny_config(
            "savn",
            "algo=ppo",
            "ppo.envs=8",
            "frames=100",
            "model.inner_lr=0.1",
            f"env.max_steps={max_steps}",
            *extra,
        )
        trainer = PPOTrainer(config, None, fixture_library)
        trainer.build()
        return trainer.collector.collect(max_steps, trainer.rng)

    cut = collect(8, "ppo.bootstrap_time_limit=true")
    longer = collect(9, "ppo.bootstrap_time_limit=true")
    truncated = cut.truncated[7]
    assert truncated.any(), "some fixture episodes should run to the limit"
    assert not cut.terminated[7][truncated].any()
    assert torch.equal(cut.actions, longer.actions[:8])
    assert torch.allclose(cut.bootstrap[7][truncated], longer.values[8][truncated], atol=1e-5)
    assert (cut.bootstrap[:7] == 0).all() and (cut.bootstrap[7][~truncated] == 0).all()
    references = collect(8)
    assert not references.truncated.any() and torch.equal(
        references.terminated[7], cut.terminated[7] | truncated
    )
    assert (references.bootstrap == 0).all()


@pytest.mark.parametrize("model", ["savn", "cvmeta"])
def test_adaptive_replay_meta_gradient_is_the_sum_of_per_episode_ones(model: str) -> None:
    trainer = PPOTrainer(
        tiny_config(model, "algo=ppo", "ppo.envs=3", "ppo.minibatches=1", "frames=100"),
        None,
        fixture_library,
    )
    trainer.build()
    segment = trainer.collector.collect(8, trainer.rng)
    torch.manual_seed(1)
    weights = torch.randn(8, 3, 6)

    def gradient(columns: list[int]) -> list[torch.Tensor]:
        trainer.optimizer.zero_grad(set_to_none=True)
        index = torch.tensor(columns)
        obs = {k: v[:, index] for k, v in segment.obs.items()}
        logits, values, state = trainer.inner.replay(
            obs, segment.prev_policy[:, index], segment.mask[:, index] > 0
        )
        steps = logits.shape[0]
        mask = segment.mask[:steps, index]
        objective = ((logits * weights[:steps, index]).sum(-1) + values) * mask
        trainer.inner.backward(state, objective.sum())
        return [p.grad.clone() if p.grad is not None else torch.zeros_like(p) for p in trainer.params]

    batched = gradient([0, 1, 2])
    separate = [gradient([b]) for b in range(3)]
    for i, g in enumerate(batched):
        total = sum(s[i] for s in separate)
        assert torch.allclose(g, total, atol=1e-5, rtol=1e-4), i
    assert any(g.abs().sum() > 0 for g in batched)


@pytest.mark.parametrize("model", ["a3c", "savn"])
def test_ppo_run_resumes_exactly(tmp_path: Path, model: str) -> None:
    overrides = ("algo=ppo", "ppo.envs=4", "ppo.steps=6", "ppo.minibatches=2", "ppo.epochs=2", "episodes=0")
    config = tiny_config(model, *overrides, "frames=96", "checkpoint_every=1", "log_every=2")
    straight = tmp_path / "straight"
    summary = train(config, straight, library_factory=fixture_library)
    assert summary["frames"] >= 96 and summary["episodes"] > 0
    halted = tmp_path / "halted"
    train(config.replace(frames=48), halted, library_factory=fixture_library)
    resumed_config, state = resume_config(halted, ["frames=96"])
    train(resumed_config, halted, resume=state, library_factory=fixture_library)
    a, b = ckpt.load_file(straight / ckpt.CHECKPOINT_FILE), ckpt.load_file(halted / ckpt.CHECKPOINT_FILE)
    assert a["counters"] == b["counters"]
    for key, value in a["model"].items():
        assert torch.equal(value, b["model"][key]), key
    records = (straight / "metrics.jsonl").read_text()
    for key in ("ppo/approx_kl", "ppo/clip_fraction", "ppo/explained_variance", "charts/success"):
        assert key in records


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("ppo.minibatches=8", "at least as many slots"),
        ("ppo.lr=nan", "ppo.lr"),
        ("ppo.lam=1.5", "ppo.lam"),
        ("a3c.mode=async", r"a3c\.mode.*algo is ppo"),
        ("a3c.precision=bf16", r"a3c\.precision.*algo is ppo"),
    ],
)
def test_impossible_ppo_settings_are_clear_errors(override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        tiny_config("a3c", "algo=ppo", "ppo.envs=4", override)


def test_only_the_chosen_algorithms_block_may_be_set() -> None:
    message = r"config key 'a3c\.amsgrad': algo is ppo, which reads only the ppo: block; remove the a3c: settings \(amsgrad, gamma\) or set algo: a3c"
    with pytest.raises(ConfigError, match=message):
        tiny_config("a3c", "algo=ppo", "ppo.envs=4", "a3c.gamma=0.9", "a3c.amsgrad=false")
    with pytest.raises(ConfigError, match=r"config key 'ppo\.gamma': algo is a3c, .* or set algo: ppo"):
        tiny_config("a3c", "ppo.gamma=0.9")
    tiny_config("a3c", "algo=ppo", "ppo.envs=4", "ppo.gamma=0.9")  # each reads its own block
    tiny_config("a3c", "a3c.gamma=0.9")


@pytest.mark.parametrize(
    "override",
    [
        "a3c.lr=inf",
        "a3c.lr=1e30",
        "env.reward.step_penalty=nan",
        "env.reward.success_reward=inf",
        "a3c.value_coef=inf",
        "ppo.lr=inf",
    ],
)
def test_non_finite_settings_are_refused(override: str) -> None:
    with pytest.raises(ConfigError, match=override.split("=")[0].replace(".", r"\.")):
        tiny_config("a3c", override)


def test_the_shortest_path_expert_succeeds_on_an_optimal_path() -> None:
    import numpy as np

    from mapless.episodes.sampler import TrainingSampler
    from mapless.sim.vector import BatchedNavEnv

    library = fixture_library()
    scenes = ["FloorPlan1", "FloorPlan2"]
    sampler = TrainingSampler(library, scenes, seed=3)  # starts always reach their target
    rng = np.random.default_rng(0)
    env = BatchedNavEnv(library, scenes, 16, mode="train", max_steps=50)
    episodes = [sampler.sample(rng) for _ in range(16)]
    env.reset(np.arange(16), episodes)
    optimal = env.optimal_length.copy()
    success = np.zeros(16, dtype=bool)
    while not env.done.all():
        actions = env.expert_actions()
        assert (actions[~env.done] >= 0).all()
        success |= env.step(np.maximum(actions, 0)).success
    assert success.all()
    np.testing.assert_array_equal(env.steps, optimal)  # SPL 1: the optimal length, Done included
    assert (optimal > 1).any(), "some episodes should need moves"
    assert (env.expert_actions() == -1).all()  # nothing to say once every episode is over


def test_imitation_pulls_the_policy_toward_the_expert() -> None:
    overrides = ("algo=ppo", "ppo.envs=8", "ppo.steps=8", "ppo.minibatches=2", "episodes=0", "frames=1500")
    config = tiny_config(
        "mlp",
        *overrides,
        "ppo.imitation_coef=5",
        "ppo.entropy_coef=0",
        "ppo.lr=0.003",
        "checkpoint_every=100000",
    )
    trainer = PPOTrainer(config, None, fixture_library)
    trainer.build()
    losses = [trainer.update()["scalars"]["ppo/imitation_loss"] for _ in range(12)]
    # From chance (log 6 = 1.79 nats) the cross-entropy to the expert falls on the agent's own steps.
    assert losses[0] > 1.6
    assert np.mean(losses[-3:]) < losses[0] - 0.4


def _adaptive_trainer(*overrides: str) -> tuple[PPOTrainer, object]:
    config = tiny_config(
        "cvmeta",
        "algo=ppo",
        "ppo.envs=6",
        "ppo.minibatches=1",
        "frames=100",
        "model.inner_lr=0.1",
        *overrides,
    )
    trainer = PPOTrainer(config, None, fixture_library)
    trainer.build()
    return trainer, trainer.collector.collect(8, trainer.rng)


def _gradients(
    trainer: PPOTrainer, segment, advantages: torch.Tensor, imitation: float = 0.0
) -> dict[str, torch.Tensor | None]:
    columns = torch.arange(segment.mask.shape[1])
    returns = segment.values + advantages
    trainer.minibatch_step(segment, columns, advantages, returns, imitation)
    return {n: None if p.grad is None else p.grad.clone() for n, p in trainer.model.named_parameters()}


@pytest.mark.parametrize("navigation_loss", ["episode", "after_interaction"])
def test_the_papers_navigation_loss_reads_no_step_of_the_interaction_phase(navigation_loss: str) -> None:
    """Under ``ppo.meta.navigation_loss: after_interaction`` the first k steps of every episode are out
    of the loss: changing their advantages changes no gradient; under ``episode`` it does."""
    k = 3
    trainer, segment = _adaptive_trainer(
        f"model.interaction_steps={k}", "model.max_inner_updates=1", f"ppo.meta.navigation_loss={navigation_loss}",
        "ppo.normalize_advantages=false",
    )  # fmt: skip
    assert (segment.mask[k:].sum() > 0) and (segment.mask[:k].sum() > 0)
    torch.manual_seed(0)
    advantages = torch.randn_like(segment.values)
    changed = advantages.clone()
    changed[:k] += 5.0
    first, second = _gradients(trainer, segment, advantages), _gradients(trainer, segment, changed)
    same = all(
        (a is None and b is None) or torch.allclose(a, b, atol=1e-6)
        for a, b in zip(first.values(), second.values(), strict=True)
    )
    assert same == (navigation_loss == "after_interaction")
    assert any(g is not None and g.abs().sum() > 0 for g in first.values())


@pytest.mark.parametrize(
    ("imitation", "from_imitation", "phi_steps"), [(1.0, False, False), (1.0, True, True), (0.0, False, True)]
)
def test_the_learned_loss_takes_no_step_while_the_expert_term_is_on(
    imitation: float, from_imitation: bool, phi_steps: bool
) -> None:
    """φ learns to stand in for the navigation loss only: an update whose loss holds the expert's
    cross-entropy leaves it without gradient (unless ``ppo.meta.learned_loss_from_imitation``)."""
    trainer, segment = _adaptive_trainer(
        "ppo.imitation_coef=1", f"ppo.meta.learned_loss_from_imitation={str(from_imitation).lower()}"
    )
    torch.manual_seed(0)
    grads = _gradients(trainer, segment, torch.randn_like(segment.values), imitation)
    phi = trainer.model.learned_loss_parameter_names()
    assert phi
    has_step = [grads[n] is not None and bool(grads[n].abs().sum() > 0) for n in phi]
    assert any(has_step) == phi_steps
    assert grads["lstm.weight_ih"] is not None and grads["lstm.weight_ih"].abs().sum() > 0


def test_a_frozen_learned_loss_takes_no_step_and_the_inner_steps_still_adapt() -> None:
    """``ppo.meta.train_learned_loss: false`` (ablation row m): φ gets no gradient, θ_0 exactly the one
    it gets with φ trained (the same forward: φ starts where the seed puts it), and that gradient is
    not the one of an episode without inner steps: the fast weights still move along φ's gradient."""
    grads = {}
    for name, overrides in {
        "trained": (),
        "frozen": ("ppo.meta.train_learned_loss=false",),
        "no inner step": ("model.max_inner_updates=0",),
    }.items():
        trainer, segment = _adaptive_trainer(*overrides)
        torch.manual_seed(0)
        grads[name] = _gradients(trainer, segment, torch.randn_like(segment.values))
    phi = set(trainer.model.learned_loss_parameter_names())
    assert all(grads["frozen"][n] is None for n in phi)
    assert any(grads["trained"][n] is not None and grads["trained"][n].abs().sum() > 0 for n in phi)
    theta = [n for n, g in grads["trained"].items() if n not in phi and g is not None]
    assert "lstm.weight_ih" in theta
    for n in theta:
        torch.testing.assert_close(grads["frozen"][n], grads["trained"][n])
    assert not torch.allclose(grads["frozen"]["lstm.weight_ih"], grads["no inner step"]["lstm.weight_ih"])


def test_a_frozen_learned_loss_is_refused_outside_ppo() -> None:
    with pytest.raises(
        ConfigError, match=r"config key 'ppo.meta': algo is a3c, which reads only the a3c: block"
    ):
        tiny_config("cvmeta", "algo=a3c", "ppo.meta.train_learned_loss=false")


def test_without_meta_learning_an_adaptive_model_trains_on_segments_as_a_plain_policy() -> None:
    """``model.adapt: none``: no inner loop, segments of ``ppo.steps`` like a3c's, the learned loss
    never used (no gradient)."""
    config = tiny_config("cvmeta", "algo=ppo", "ppo.envs=4", "ppo.steps=5", "frames=100", "model.adapt=none")
    trainer = PPOTrainer(config, None, fixture_library)
    trainer.build()
    assert trainer.inner is None and not trainer.model.adaptive
    segment = trainer.collector.collect(5, trainer.rng)
    assert segment.mask.shape[0] == 5
    grads = _gradients(trainer, segment, torch.randn_like(segment.values))
    assert all(grads[n] is None for n in trainer.model.learned_loss_parameter_names())
    assert grads["lstm.weight_ih"].abs().sum() > 0


@pytest.mark.parametrize("model", ["a3c", "cvmeta"])
def test_whole_episodes_make_a_plain_policy_play_each_slots_episode_to_its_end(model: str) -> None:
    """``ppo.whole_episodes`` for a non-adaptive model: an update collects one episode per slot,
    each from step 0 to its end (not ``ppo.steps``), the slot idle and masked after it, the limit an
    end; no inner loop acts, and the replay reproduces the acting policy on every step in the loss,
    with or without the idle steps encoded."""

    def trainer_with(*extra: str) -> PPOTrainer:
        plain = ["model.adapt=none"] if model == "cvmeta" else []  # cvmeta as a plain recurrent policy
        config = tiny_config(
            model, "algo=ppo", "ppo.envs=6", "ppo.steps=3", "frames=100", "env.max_steps=9", *plain, *extra
        )
        trainer = PPOTrainer(config, None, fixture_library)
        trainer.build()
        return trainer

    trainer = trainer_with("ppo.whole_episodes=true")
    assert trainer.inner is None and not trainer.collector.adapting
    segment = trainer.collector.collect(9, trainer.rng)
    assert segment.starts[0].all() and not segment.starts[1:].any()
    assert len(segment.finished["success"]) == 6 and (segment.next_value == 0).all()
    lengths = segment.mask.sum(0).long().tolist()
    assert max(lengths) == segment.mask.shape[0] and min(lengths) < max(lengths)
    for slot, length in enumerate(lengths):
        assert (segment.mask[:length, slot] == 1).all() and (segment.mask[length:, slot] == 0).all()
        assert bool(segment.terminated[length - 1, slot]) and not segment.truncated[:, slot].any()
    logits, values = trainer.model.replay(segment.obs, segment.prev_policy, segment.starts, segment.hidden)
    log_prob = torch.log_softmax(logits, -1).gather(-1, segment.actions[..., None]).squeeze(-1)
    mask = segment.mask > 0
    assert torch.allclose(log_prob[mask], segment.log_prob[mask], atol=1e-5)
    assert torch.allclose(values[mask], segment.values[mask], atol=1e-5)
    # Encoding only the steps taken (the update's replay) changes nothing where the loss reads.
    logits_acted, values_acted = trainer.model.replay(
        segment.obs, segment.prev_policy, segment.starts, segment.hidden, acted=mask
    )
    assert torch.allclose(logits_acted[mask], logits[mask], atol=1e-6)
    assert torch.allclose(values_acted[mask], values[mask], atol=1e-6)
    assert trainer.update()["segment"].mask.shape[0] > 3  # the update plays to the episodes' end
    assert trainer_with().update()["segment"].mask.shape[0] == 3  # off: ppo.steps-step segments


def test_a_minibatch_whose_every_step_is_in_the_interaction_phase_gives_no_nan() -> None:
    """Episodes no longer than k under ``after_interaction``: nothing is in the loss, and advantage
    normalisation over no step must not turn the gradient into NaN."""
    trainer, segment = _adaptive_trainer(
        "model.interaction_steps=9", "model.max_inner_updates=1", "ppo.meta.navigation_loss=after_interaction"
    )
    assert segment.mask.shape[0] <= 9
    grads = _gradients(trainer, segment, torch.randn_like(segment.values))
    assert all(g is None or bool(torch.isfinite(g).all()) for g in grads.values())
