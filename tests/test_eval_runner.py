"""The evaluation runner on hand-made fixture scenes: oracle = perfect scores, determinism across
worker counts, seeded sampling, test-time adaptation of meta models, scene partitioning."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter

import numpy as np
import pytest
import torch
from eval_fixtures import fixture_episodes, fixture_library

from mapless.agent.evaluation import AdaptiveModelAgent, ModelAgent, OracleAgent
from mapless.errors import MaplessError
from mapless.evaluate.metrics import aggregate
from mapless.evaluate.runner import (
    AgentSpec,
    EvalSettings,
    LibrarySpec,
    evaluate,
    partition,
    run_episodes,
    target_fields,
)
from mapless.models import build_model
from mapless.sim.vector import BatchedNavEnv

LIBRARY = LibrarySpec(factory="eval_fixtures:fixture_library")


pytestmark = pytest.mark.usefixtures("single_torch_thread")


@pytest.fixture(scope="module")
def episodes():
    return fixture_episodes(per_scene=12)


def trajectories(run):
    return [(r.index, r.success, r.length, r.poses, r.actions) for r in run.results]


def test_oracle_scores_perfectly(episodes):
    run = evaluate(AgentSpec(kind="oracle"), episodes, EvalSettings(batch_size=5, workers=1), LIBRARY)
    m = aggregate(run.results)
    assert m["success"] == 1.0 and m["spl"] == 1.0 and m["l5_spl"] == 1.0
    assert m["done_rate"] == 1.0 and m["failed_action_rate"] == 0.0
    assert [r.length for r in run.results] == [e.optimal_length for e in episodes]
    assert [r.index for r in run.results] == list(range(len(episodes)))
    # The path is the pose sequence: it ends where the target is visible.
    lib = fixture_library()
    for r, e in zip(run.results, episodes, strict=True):
        data = lib[e.scene]
        assert data.target_distances(e.target)[r.poses[-1]] == 0
    # It first sees the target where it stops: its last move (the start, for a one-step episode).
    assert [r.first_seen for r in run.results] == [r.length - 1 for r in run.results]
    assert all(r.ended_in_frame for r in run.results)
    assert all(r.stops_passed == 0 for r in run.results)  # it stops where it first could


def test_no_episodes_is_an_error_naming_the_agent_not_an_index_error():
    with pytest.raises(MaplessError, match="no episodes to evaluate oracle on"):
        evaluate(AgentSpec(kind="oracle"), [], EvalSettings(workers=1), LIBRARY)


@pytest.mark.slow
def test_results_independent_of_workers_and_batch_neighbours(episodes):
    spec = AgentSpec(model={"name": "a3c", "hidden_size": 64}, init_seed=3)
    one = evaluate(spec, episodes, EvalSettings(batch_size=6, workers=1, seed=7), LIBRARY)
    two = evaluate(spec, episodes, EvalSettings(batch_size=6, workers=2, seed=7), LIBRARY)
    assert trajectories(one) == trajectories(two)
    # Reversed order (same set positions): other episodes share each batch, same trajectories.
    n = len(episodes)
    rev = run_episodes(
        spec.build(6),
        fixture_library(),
        episodes[::-1],
        list(range(n))[::-1],
        EvalSettings(batch_size=6, seed=7),
    )
    assert trajectories(type(one)(rev, 1.0, 1)) == trajectories(one)
    other_seed = evaluate(spec, episodes, EvalSettings(batch_size=6, workers=1, seed=8), LIBRARY)
    assert trajectories(other_seed) != trajectories(one)


def test_random_policy_samples_uniformly_and_respects_limits(episodes):
    run = evaluate(
        AgentSpec(model={"name": "random"}), episodes * 4, EvalSettings(batch_size=16, workers=1), LIBRARY
    )
    counts = Counter(a for r in run.results for a in r.actions)
    total = sum(counts.values())
    assert set(counts) == set(range(6))
    for a in range(6):
        assert abs(counts[a] / total - 1 / 6) < 0.05
    for r in run.results:
        limit = 200 if r.room_type == "living_room" else 100
        assert r.length <= limit
        assert r.called_done == (r.actions[-1] == 5)
        assert r.called_done or r.length == limit
    # Every success saw its target (at the latest where it stopped); a walk of 100 steps sees more
    # targets than the few Dones that end on one.
    assert all(0 <= r.first_seen <= r.length - 1 for r in run.results if r.success)
    assert all(-1 <= r.first_seen <= r.length for r in run.results)
    assert sum(r.first_seen >= 0 for r in run.results) > sum(r.success for r in run.results)
    # A random walk passes stops up: none before its first sight, and every failure that saw its
    # target before its last action passed at least the stop where it saw it.
    assert all(r.stops_passed == 0 for r in run.results if r.first_seen == -1)
    failed_after_a_sight = [r for r in run.results if 0 <= r.first_seen < r.length and not r.success]
    assert failed_after_a_sight and all(r.stops_passed >= 1 for r in failed_after_a_sight)
    assert sum(r.stops_passed for r in run.results) > 0
    # Where it ended, a target instance is in the frame exactly when the scene's view list says so.
    lib, by_index = fixture_library(), episodes * 4
    for r in run.results:
        data, e = lib[r.scene], by_index[r.index]
        in_view = set(data.in_view(r.poses[-1]).tolist()) & set(
            data.goal_instances(e.target, e.target_ids).tolist()
        )
        assert r.ended_in_frame == bool(in_view)
    assert any(r.ended_in_frame and not r.success for r in run.results if r.called_done)


def test_greedy_ignores_the_sampling_seed(episodes):
    spec = AgentSpec(model={"name": "a3c", "hidden_size": 64}, init_seed=0)
    a = evaluate(spec, episodes[:8], EvalSettings(batch_size=4, workers=1, seed=1, greedy=True), LIBRARY)
    b = evaluate(spec, episodes[:8], EvalSettings(batch_size=4, workers=1, seed=2, greedy=True), LIBRARY)
    assert trajectories(a) == trajectories(b)


def test_adaptive_agent_adapts_every_k_steps_and_resets_per_episode(episodes):
    torch.manual_seed(0)
    model = build_model("savn", hidden_size=64)
    batch = 3
    agent = AdaptiveModelAgent(model, batch)
    assert agent.start_every == model.config.interaction_steps == 6
    library = fixture_library()
    env = BatchedNavEnv(
        library, ["FloorPlan5", "FloorPlan205"], batch, targets=target_fields("mjolnir101"), mode="eval"
    )
    slots = np.arange(batch)
    env.reset(slots, episodes[:batch])
    agent.start(slots, env)
    theta = {n: p.detach().clone() for n, p in model.named_parameters()}
    for _ in range(6):
        probs = agent.policy(env.observe(agent.observation_keys), env)
        actions = np.zeros(batch, dtype=np.int64)  # MoveAhead keeps every episode alive
        agent.after_step(actions, env.step(actions))
    assert agent.updates.tolist() == [1, 1, 1]
    name = "actor_linear.weight"
    moved = (agent.adapter.state.fast[name] - theta[name]).abs().amax(dim=(1, 2))
    assert bool((moved > 0).all())
    block = slice(0, agent.k)  # the LSTM matrices' first inner step: each slot's first factor block
    assert bool((agent.adapter.state.left[:, block].abs().amax(dim=(1, 2)) > 0).all())
    assert not agent.adapter.state.left[:, agent.k :].any()
    # φ and θ themselves never change; a new episode starts again from θ.
    for n, p in model.named_parameters():
        assert torch.equal(p, theta[n])
    agent.start(np.array([1]), env)
    assert torch.equal(agent.adapter.state.fast[name][1], theta[name])
    assert not agent.adapter.state.left[1].any() and agent.adapter.state.left[0].any()
    assert agent.updates.tolist() == [1, 0, 1]
    assert probs.shape == (batch, 6)


def test_test_time_step_matches_the_training_inner_loop(episodes):
    """The evaluator's in-place step with per-slot factor blocks gives the same policy as the
    training inner loop's (differentiable, growing-factor) step on the same rows."""
    from mapless.agent.meta import InnerLoop, TestTimeAdaptation
    from mapless.models.synthetic import synthetic_observations

    torch.manual_seed(1)
    model = build_model("cvmeta", hidden_size=32).eval()
    training = InnerLoop(model)  # before the agent freezes θ and φ
    train_state = training.start(3)
    before = TestTimeAdaptation(model)
    agent = AdaptiveModelAgent(model, 3)
    agent.adapter.loop.reset_slots(agent.adapter.state, torch.arange(3))
    obs = synthetic_observations(3, model.knowledge)
    due = torch.tensor([True, False, True])
    logits = []
    for loop, state in ((training, train_state), (agent.adapter.loop, agent.adapter.state)):
        hidden, prev, rows = model.initial_state(3), torch.zeros(3, 6), []
        for _ in range(6):
            out = loop.forward(state, obs, hidden, prev)
            hidden, prev = out.hidden, torch.softmax(out.logits, dim=-1)
            rows.append(torch.cat([hidden[0], prev], dim=-1))
        loop.adapt(state, torch.stack(rows, dim=1), due)
        logits.append(loop.forward(state, obs, hidden, prev).logits.detach())
    torch.testing.assert_close(logits[1], logits[0], rtol=1e-5, atol=1e-6)
    assert agent.adapter.state.slot_updates.tolist() == [1, 0, 1]
    fresh = before.start(3)
    hidden, prev = model.initial_state(3), torch.zeros(3, 6)
    for _ in range(6):
        out = before.forward(fresh, obs, hidden, prev)
        hidden, prev = out.hidden, torch.softmax(out.logits, dim=-1)
    unadapted = before.forward(fresh, obs, hidden, prev).logits.detach()
    assert torch.equal(unadapted[1], logits[1][1]) and not torch.allclose(unadapted[0], logits[1][0])


def test_adaptive_model_evaluates_end_to_end(episodes):
    spec = AgentSpec(model={"name": "savn", "hidden_size": 64}, init_seed=0)
    run = evaluate(spec, episodes[:10], EvalSettings(batch_size=4, workers=1), LIBRARY)
    assert [r.index for r in run.results] == list(range(10))
    assert all(1 <= r.length <= 200 for r in run.results)


def test_run_episodes_in_process_matches_oracle_lengths(episodes):

    results = run_episodes(
        OracleAgent(4), fixture_library(), episodes[:6], [10, 11, 12, 13, 14, 15], EvalSettings(batch_size=4)
    )
    assert [r.index for r in results] == [10, 11, 12, 13, 14, 15]
    assert [r.length for r in results] == [e.optimal_length for e in episodes[:6]]


def test_partition_keeps_scenes_whole_and_balances(episodes):
    shares = partition(episodes, 2)
    assert sorted(i for s in shares for i in s) == list(range(len(episodes)))
    scenes = [{episodes[i].scene for i in s} for s in shares]
    assert scenes[0].isdisjoint(scenes[1])
    assert partition(episodes, 5) == [s for s in partition(episodes, 5) if s]
    assert len(partition(episodes, 5)) == 2  # only two scenes to share out


def test_bf16_evaluation_is_training_precision_and_float32_up_to_rounding():
    """``bf16`` means one thing: the evaluator's policy at bf16 is the training actor's at
    ``a3c.precision: bf16`` (bfloat16 encoders and LSTM products), and float32's up to rounding."""
    from mapless.models.synthetic import synthetic_observations
    from mapless.train.rollout import make_actor

    torch.manual_seed(0)
    model = build_model("mjolnir_o", hidden_size=64)
    synthetic = synthetic_observations(4, model.knowledge)
    obs = {k: v.numpy() for k, v in synthetic.items()}
    exact = ModelAgent(model, 4).policy(obs, None)
    fast_agent = ModelAgent(model, 4, bf16=True)
    fast = fast_agent.policy(obs, None)
    assert fast.dtype == exact.dtype and fast_agent.memory.hidden[0].dtype == torch.float32
    np.testing.assert_allclose(fast, exact, atol=2e-3)
    assert not np.array_equal(fast, exact)
    np.testing.assert_allclose(fast.sum(axis=1), 1.0, atol=1e-6)

    actor = make_actor(model, precision="bf16")
    actor.start(4)
    hidden, prev_policy = model.initial_state(4), torch.zeros(4, 6)
    training = torch.softmax(actor.forward(synthetic, hidden, prev_policy).logits, -1).detach().numpy()
    np.testing.assert_array_equal(fast, training)


_POOL_THEN_DIE = """
import multiprocessing, os
from concurrent.futures import ProcessPoolExecutor
from mapless.processes import exit_with_parent
if __name__ == "__main__":
    watch = {watch}
    init = dict(initializer=exit_with_parent, initargs=(os.getpid(), 0.1)) if watch else {{}}
    pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"), **init)
    print(pool.submit(os.getpid).result(), flush=True)
    os._exit(0)  # no shutdown, as a parent killed by a signal leaves its pool
"""


@pytest.mark.slow
@pytest.mark.parametrize("watch", [True, False])
def test_evaluation_workers_exit_when_their_parent_dies(watch: bool) -> None:
    parent = subprocess.Popen([sys.executable, "-c", _POOL_THEN_DIE.format(watch=watch)],
                              stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              text=True)  # fmt: skip
    worker = int(parent.stdout.readline())
    parent.wait(timeout=60)
    deadline = time.monotonic() + 20
    while _running(worker) and time.monotonic() < deadline and watch:
        time.sleep(0.1)
    orphaned = _running(worker)
    if orphaned:
        os.kill(worker, signal.SIGKILL)
    # Without the initializer the worker blocks on its call queue forever: the test can fail.
    assert orphaned is not watch


def _running(pid: int) -> bool:
    state = subprocess.run(
        ["ps", "-o", "stat=", "-p", str(pid)], capture_output=True, text=True
    ).stdout.strip()
    return bool(state) and not state.startswith("Z")
