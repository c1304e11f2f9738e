"""Every form of the policy's recurrent step, on every registered model family, computes what the
plain computation computes: outputs, recurrent state and parameter gradients.

Forms: the plain ``forward``; ``rollout_step`` through a rollout's LSTM weight products (float64, and
bf16 in train mode with dropout); ``replay`` of a recorded segment, time-batched, with episode starts
inside it; the meta-learning inner loop with per-episode fast weights (second order, first order,
bf16); test-time adaptation; ``predict_values``.

In float64 every form but ``forward`` is compared with the same computation written out plainly in
this file and run in the same process (``forward`` stepped by hand; one episode at a time through
``functional_call`` with its adapted matrices materialised; plain autograd for the meta-gradients), at
1e-9 of the value: the forms differ from it by summation order alone, so a change in what they compute
fails whatever CPU runs the test. The plain ``forward`` and the bf16 forms have no such reference:
they are compared with values recorded in tests/data/policy_step_golden.pt. Another CPU moves those
float64 values by up to 3.3e-5 of their size (through what a model computes in float32 before
``.to(float64)``), so they are held to 2e-4 of the value plus 1e-9, and the bf16 ones, rounded to 8
bits, more loosely still. On the machine that recorded, ``MAPLESS_GOLDEN_EXACT=1`` asks for bit-for-bit
equality.

Re-record only on purpose (a change of arithmetic): ``python tests/test_policy_step.py --record``.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from functools import cache
from pathlib import Path

import pytest
import torch
from torch.func import functional_call

from mapless.agent.acting import AdaptingActor
from mapless.agent.meta import InnerLoop
from mapless.agent.rollout_lstm import RolloutLstm
from mapless.knowledge import synthetic_knowledge
from mapless.models import build_model
from mapless.models.base import NavModel
from mapless.models.registry import MODELS
from mapless.models.synthetic import synthetic_observations
from mapless.train.a3c_loss import a3c_loss

GOLDEN = Path(__file__).parent / "data" / "policy_step_golden.pt"
RECURRENT = ["a3c", "sp", "savn", "gve", "spatt", "mjolnir_o", "mjolnir_r", "cvmeta", "mlp"]
ADAPTIVE = ["savn", "gve", "spatt", "cvmeta", "cvmeta-all"]  # cvmeta-all: adapt: all
#: models whose encoder does not read the recurrent state (PPO's segment replay needs that)
REPLAYED = ["a3c", "sp", "mjolnir_o", "mjolnir_r", "mlp", "savn", "cvmeta-none"]
STEPS, BATCH = 5, 3
LENGTHS = (5, 3, 2)  # whole episodes of the fast-weight runs end at different steps
#: (rtol, atol) per dtype of the recorded values
#: (bf16 rounds intermediates to 8 bits: another CPU's kernels may move them by far more than fp64's).
#: ``MAPLESS_GOLDEN_EXACT=1`` asks for bit-for-bit equality (on the machine that recorded).
TOLERANCE = {torch.float64: (2e-4, 1e-9), torch.float32: (2e-2, 2e-3)}
EXACT = os.environ.get("MAPLESS_GOLDEN_EXACT") == "1"


def _model(name: str, dtype: torch.dtype = torch.float64, dropout: float = 0.0) -> NavModel:
    torch.manual_seed(0)
    family, _, adapt = name.partition("-")
    model = build_model(
        family,
        knowledge=synthetic_knowledge(5, 300, seed=1),
        hidden_size=16,
        fusion_channels=2,
        interaction_steps=2,
        max_inner_updates=2,
        inner_lr=0.05 if MODELS[family].is_adaptive() else None,
        adapt=adapt or None,
        dropout=dropout,
    )
    return model.to(dtype).eval()


def _inputs(model: NavModel, dtype: torch.dtype, seed: int = 0):
    """``STEPS`` observation batches, actions, rewards and a non-zero starting state."""
    gen = torch.Generator().manual_seed(seed)
    obs = []
    for _ in range(STEPS):
        o = synthetic_observations(BATCH, model.knowledge, model.feature_channels, generator=gen)
        obs.append({k: (v.to(dtype) if v.is_floating_point() else v) for k, v in o.items()})
    actions = torch.randint(0, 6, (STEPS, BATCH), generator=gen)
    rewards = torch.randn(STEPS, BATCH, generator=gen, dtype=dtype)
    hidden = tuple(0.5 * torch.randn(BATCH, model.hidden_size, generator=gen, dtype=dtype) for _ in range(2))
    return obs, actions, rewards, hidden


def _loss(logits: list[torch.Tensor], values: list[torch.Tensor], actions, rewards, mask=None):
    mask = torch.ones_like(rewards) if mask is None else mask
    stacked = torch.stack([v.reshape(-1) for v in values])
    return a3c_loss(torch.stack(logits), stacked, actions, rewards, mask).total.sum()


def _fingerprint(model: NavModel, grads: dict[str, torch.Tensor | None]) -> dict[str, torch.Tensor]:
    """Per parameter gradient: its sum, a fixed random projection and its first entries (the full
    gradients of the LSTM matrices would make the file megabytes)."""
    out = {}
    for name, g in grads.items():
        if g is None:
            continue
        flat = g.detach().double().flatten()
        gen = torch.Generator().manual_seed(len(name))
        direction = torch.randn(flat.numel(), generator=gen, dtype=flat.dtype)
        summary = torch.cat([flat.sum().view(1), (flat * direction).sum().view(1), flat[:8]])
        out[f"grad.{name}"] = summary.to(g.dtype)
    return out


def _param_grads(model: NavModel) -> dict[str, torch.Tensor | None]:
    return {n: p.grad for n, p in model.named_parameters() if p.requires_grad}


def _outputs(prefix: str, logits, values, hidden=None) -> dict[str, torch.Tensor]:
    out = {f"{prefix}.logits": torch.stack(logits).detach(), f"{prefix}.values": torch.stack(values).detach()}
    if hidden is not None:
        out[f"{prefix}.h"], out[f"{prefix}.c"] = (t.detach() for t in hidden)
    return out


# -- the variants, through the policy's entry points ---------------------------------------------------
def run_forward(name: str) -> dict[str, torch.Tensor]:
    """``model(obs, hidden, prev_policy)`` stepped through an episode, and the gradient of a loss."""
    model = _model(name)
    obs, actions, rewards, hidden = _inputs(model, torch.float64)
    policy = torch.zeros(BATCH, 6, dtype=torch.float64)
    logits, values = [], []
    for t in range(STEPS):
        out = model(obs[t], hidden, policy)
        logits.append(out.logits)
        values.append(out.value)
        hidden, policy = out.hidden, torch.softmax(out.logits, -1)
    result = _outputs("forward", logits, values, hidden)
    if any(p.requires_grad for p in model.parameters()):
        _loss(logits, values, actions, rewards).backward()
        result |= _fingerprint(model, _param_grads(model))
    return result


def run_step(name: str, precision: str) -> dict[str, torch.Tensor]:
    """One step at a precision through a recording :class:`RolloutLstm` (the A3C actor's and the
    evaluator's step), gradients through its deferred weight gradient. bf16 runs in train mode, so
    the dropout masks' draws are part of what must not change."""
    bf16 = precision == "bf16"
    dtype = torch.float32 if bf16 else torch.float64
    model = _model(name, dtype, dropout=0.25 if bf16 else 0.0)
    model.train(bf16)
    obs, actions, rewards, hidden = _inputs(model, dtype)
    lstm = RolloutLstm(model.recurrent_cell, dtype=torch.bfloat16 if bf16 else None)
    policy = torch.zeros(BATCH, 6, dtype=dtype)
    torch.manual_seed(1)
    logits, values = [], []
    for t in range(STEPS):
        out = model.rollout_step(obs[t], hidden, policy, lstm)
        logits.append(out.logits)
        values.append(out.value)
        hidden, policy = out.hidden, torch.softmax(out.logits, -1)
    params = dict((n, p) for n, p in model.named_parameters() if p.requires_grad)
    grads = lstm.grad(_loss(logits, values, actions, rewards), list(params.values()))
    return _outputs(f"step_{precision}", logits, values, hidden) | _fingerprint(
        model, dict(zip(params, grads, strict=True))
    )


def run_replay(name: str) -> dict[str, torch.Tensor]:
    """A recorded segment replayed time-batched, with episode starts inside it (PPO's update)."""
    model = _model(name)
    obs, actions, rewards, hidden = _inputs(model, torch.float64)
    stacked = {k: torch.stack([o[k] for o in obs]) for k in obs[0]}
    gen = torch.Generator().manual_seed(3)
    prev_policy = torch.softmax(torch.randn(STEPS, BATCH, 6, generator=gen, dtype=torch.float64), -1)
    starts = torch.zeros(STEPS, BATCH, dtype=torch.bool)
    starts[2, 1] = starts[4, 0] = True
    logits, values = model.replay(stacked, prev_policy, starts, hidden)
    _loss(list(logits), list(values), actions, rewards).backward()
    return _outputs("replay", list(logits), list(values)) | _fingerprint(model, _param_grads(model))


def run_fast(name: str, mode: str) -> dict[str, torch.Tensor]:
    """Whole episodes through the meta-learning inner loop with per-episode fast weights, ended
    episodes compacted away as PPO's replay does; the meta-gradient of an A3C loss."""
    bf16 = mode == "bf16"
    dtype = torch.float32 if bf16 else torch.float64
    model = _model(name, dtype)
    obs, actions, rewards, _ = _inputs(model, dtype)
    loop = InnerLoop(model, first_order=mode == "first", dtype=torch.bfloat16 if bf16 else None)
    mask = torch.stack([torch.arange(STEPS) < n for n in LENGTHS], dim=1).to(dtype)
    state = loop.start(BATCH)
    hidden = tuple(t.to(dtype) for t in model.initial_state(BATCH))
    rows = torch.arange(BATCH)
    policy = torch.zeros(BATCH, 6, dtype=dtype)
    logits, values = [], []
    for t in range(STEPS):
        out = loop.forward(state, {k: v.index_select(0, rows) for k, v in obs[t].items()}, hidden, policy)
        logits.append(out.logits.new_zeros(BATCH, 6).index_copy(0, rows, out.logits))
        values.append(out.value.new_zeros(BATCH, 1).index_copy(0, rows, out.value))
        alive = torch.tensor([t + 1 < LENGTHS[r] for r in rows.tolist()])
        loop.observe(state, out, alive)
        hidden, policy = out.hidden, torch.softmax(out.logits, -1)
        if t + 1 < STEPS and not bool(alive.all()):
            keep = alive.nonzero().squeeze(1)
            loop.compact(state, keep)
            rows = rows.index_select(0, keep)
            hidden, policy = tuple(h.index_select(0, keep) for h in hidden), policy.index_select(0, keep)
    loop.backward(state, _loss(logits, values, actions, rewards, mask))
    return _outputs(f"fast_{mode}", logits, values) | _fingerprint(model, _param_grads(model))


def run_test_time(name: str) -> dict[str, torch.Tensor]:
    """Test-time adaptation: slots adapt in place, one slot restarts mid-way; the value alone of
    the last state under the adapted weights."""
    model = _model(name)
    obs, _, _, _ = _inputs(model, torch.float64)
    actor = AdaptingActor(model, BATCH)  # θ frozen while it acts
    actor.reset_slots(torch.arange(BATCH))
    hidden = tuple(t.double() for t in model.initial_state(BATCH))
    policy = torch.zeros(BATCH, 6, dtype=torch.float64)
    logits, values = [], []
    for t in range(STEPS):
        out = actor.forward(obs[t], hidden, policy)
        logits.append(out.logits)
        values.append(out.value)
        actor.observe(out, torch.ones(BATCH, dtype=torch.bool))
        hidden, policy = out.hidden, torch.softmax(out.logits, -1)
        if t == 3:  # at a k-step boundary, as the evaluator starts episodes
            actor.reset_slots(torch.tensor([1]))
    last = actor.value(obs[0], hidden, policy)
    actor.close()
    return _outputs("test_time", logits, values) | {"test_time.last_value": last.detach()}


def run_value(name: str) -> dict[str, torch.Tensor]:
    """The value alone of a state (a truncation's bootstrap), without a graph."""
    model = _model(name)
    obs, _, _, hidden = _inputs(model, torch.float64)
    policy = torch.softmax(torch.arange(6, dtype=torch.float64).expand(BATCH, 6), -1)
    return {"value": model.predict_values(obs[1], hidden, policy)}


CASES: dict[str, Callable[[], dict[str, torch.Tensor]]] = {
    **{f"forward/{m}": (lambda m=m: run_forward(m)) for m in ["random", *RECURRENT]},
    **{f"step_fp32/{m}": (lambda m=m: run_step(m, "fp32")) for m in RECURRENT},
    **{f"step_bf16/{m}": (lambda m=m: run_step(m, "bf16")) for m in RECURRENT},
    **{f"replay/{m}": (lambda m=m: run_replay(m)) for m in REPLAYED},
    **{f"fast_{o}/{m}": (lambda m=m, o=o: run_fast(m, o)) for o in ("second", "first") for m in ADAPTIVE},
    **{f"fast_bf16/{m}": (lambda m=m: run_fast(m, "bf16")) for m in ("savn", "cvmeta")},
    **{f"test_time/{m}": (lambda m=m: run_test_time(m)) for m in ADAPTIVE},
    **{f"value/{m}": (lambda m=m: run_value(m)) for m in RECURRENT},
}


# -- the same computations written out plainly: each variant but the bf16 ones has one ----------------
def _renamed(outputs: dict[str, torch.Tensor], old: str, new: str) -> dict[str, torch.Tensor]:
    return {
        (new + key.removeprefix(old) if key.startswith(old + ".") else key): v for key, v in outputs.items()
    }


def reference_replay(name: str) -> dict[str, torch.Tensor]:
    """:func:`run_replay`'s segment as ``T`` calls of ``forward``, the state zeroed where an episode starts."""
    model = _model(name)
    obs, actions, rewards, (h, c) = _inputs(model, torch.float64)
    gen = torch.Generator().manual_seed(3)
    prev_policy = torch.softmax(torch.randn(STEPS, BATCH, 6, generator=gen, dtype=torch.float64), -1)
    starts = torch.zeros(STEPS, BATCH, dtype=torch.bool)
    starts[2, 1] = starts[4, 0] = True
    logits, values = [], []
    for t in range(STEPS):
        keep = (~starts[t]).to(torch.float64).unsqueeze(-1)
        out = model(obs[t], (h * keep, c * keep), prev_policy[t])
        logits.append(out.logits)
        values.append(out.value.reshape(-1))
        h, c = out.hidden
    _loss(logits, values, actions, rewards).backward()
    return _outputs("replay", logits, values) | _fingerprint(model, _param_grads(model))


def _adapted(
    model: NavModel,
    theta: dict[str, torch.Tensor],
    rows: list[torch.Tensor],
    graph: bool,
    shift: bool = False,
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """One inner SGD step of one episode on its k rows ``[h_t || π_t]``, every adapted matrix
    materialised: ``(θ - α g, g)``, g only for the parameters the learned loss reaches. ``graph``:
    g keeps its graph; ``shift``: θ moves by the constant ``α g`` (first order)."""
    loss = model.learned_loss(torch.cat(rows).unsqueeze(0))[0]
    grads = torch.autograd.grad(loss, list(theta.values()), create_graph=graph, allow_unused=True)
    g = {n: d for n, d in zip(theta, grads, strict=True) if d is not None}
    step = {n: model.inner_lr * (d.detach() if shift else d) for n, d in g.items()}
    return {n: theta[n] - step[n] if n in step else theta[n] for n in theta}, g


def reference_fast(name: str, mode: str) -> dict[str, torch.Tensor]:
    """:func:`run_fast` one episode at a time through ``functional_call`` with its own θ, plain autograd
    for the meta-gradient. Second order: backpropagate through the inner steps. First order: the inner
    step shifts θ by a constant, and φ gets ``-α Σ_i <∂g_i/∂φ, ∂L/∂θ_{i+1}>``."""
    model = _model(name)
    obs, actions, rewards, _ = _inputs(model, torch.float64)
    k, limit = model.config.interaction_steps, model.config.max_inner_updates
    params = dict(model.named_parameters())
    zero = torch.zeros(1, 6, dtype=torch.float64)
    logits: list[list[torch.Tensor]] = [[] for _ in range(STEPS)]
    values: list[list[torch.Tensor]] = [[] for _ in range(STEPS)]
    shifts = []  # first order: (g_i, θ_{i+1}) of every inner step of every episode
    for b, length in enumerate(LENGTHS):
        theta = {n: params[n] for n in model.inner_parameter_names()}
        hidden = tuple(t.double() for t in model.initial_state(1))
        policy, rows, updates = zero, [], 0
        for t in range(STEPS):
            if t >= length:
                logits[t].append(zero)
                values[t].append(zero[:, :1])
                continue
            out = functional_call(
                model, theta, ({key: v[b : b + 1] for key, v in obs[t].items()}, hidden, policy)
            )
            logits[t].append(out.logits)
            values[t].append(out.value)
            hidden, policy = out.hidden, torch.softmax(out.logits, -1)
            rows.append(torch.cat([hidden[0], policy], -1))
            if len(rows) == k:
                if updates < limit and t + 1 < length:
                    theta, g = _adapted(model, theta, rows, graph=True, shift=mode == "first")
                    if mode == "first":
                        shifts.append((g, {n: theta[n] for n in g}))
                    updates += 1
                rows = []
    mask = torch.stack([torch.arange(STEPS) < n for n in LENGTHS], dim=1).to(torch.float64)
    stacked_logits, stacked_values = (
        [torch.cat(step) for step in logits],
        [torch.cat(step) for step in values],
    )
    loss = _loss(stacked_logits, stacked_values, actions, rewards, mask)
    if shifts:
        after = [theta_next[n] for _, theta_next in shifts for n in theta_next]
        v = iter(torch.autograd.grad(loss, after, retain_graph=True))
        inner = sum((g[n] * next(v)).sum() for g, theta_next in shifts for n in theta_next)
        phi = [params[n] for n in model.learned_loss_parameter_names()]
        for p, d in zip(
            phi, torch.autograd.grad(-model.inner_lr * inner, phi, retain_graph=True), strict=True
        ):
            p.grad = d
    loss.backward()
    return _outputs(f"fast_{mode}", stacked_logits, stacked_values) | _fingerprint(model, _param_grads(model))


def reference_test_time(name: str) -> dict[str, torch.Tensor]:
    """:func:`run_test_time` one slot at a time through ``functional_call``: every k steps θ takes the
    inner step (up to the update limit); slot 1 starts again from the trained θ after step 3."""
    model = _model(name)
    obs, _, _, _ = _inputs(model, torch.float64)
    k, limit = model.config.interaction_steps, model.config.max_inner_updates
    trained = {n: p.detach() for n, p in model.named_parameters() if n in model.inner_parameter_names()}
    logits, values, last = [], [], []
    for b in range(BATCH):
        theta = {n: w.clone().requires_grad_() for n, w in trained.items()}
        hidden = tuple(t.double() for t in model.initial_state(1))
        policy, rows, updates = torch.zeros(1, 6, dtype=torch.float64), [], 0
        slot_logits, slot_values = [], []
        for t in range(STEPS):
            if not rows:  # the inner step reads the chunk's own steps only: θ changed in between
                hidden, policy = tuple(s.detach() for s in hidden), policy.detach()
            single = {key: v[b : b + 1] for key, v in obs[t].items()}
            out = functional_call(model, theta, (single, hidden, policy))
            slot_logits.append(out.logits.detach())
            slot_values.append(out.value.detach())
            hidden, policy = out.hidden, torch.softmax(out.logits, -1)
            rows.append(torch.cat([hidden[0], policy], -1))
            if len(rows) == k:
                if updates < limit:
                    adapted, _ = _adapted(model, theta, rows, graph=False)
                    theta = {n: w.detach().requires_grad_() for n, w in adapted.items()}
                    updates += 1
                rows = []
            if t == 3 and b == 1:
                theta = {n: w.clone().requires_grad_() for n, w in trained.items()}
                updates = 0
        with torch.no_grad():
            last.append(
                functional_call(
                    model, theta, ({key: v[b : b + 1] for key, v in obs[0].items()}, hidden, policy)
                ).value.reshape(-1)
            )
        logits.append(torch.cat(slot_logits))
        values.append(torch.cat(slot_values))
    stacked_logits = [torch.stack([slot[t] for slot in logits]) for t in range(STEPS)]
    stacked_values = [torch.stack([slot[t] for slot in values]) for t in range(STEPS)]
    return _outputs("test_time", stacked_logits, stacked_values) | {"test_time.last_value": torch.cat(last)}


def reference_value(name: str) -> dict[str, torch.Tensor]:
    """:func:`run_value`'s state through the plain forward."""
    model = _model(name)
    obs, _, _, hidden = _inputs(model, torch.float64)
    policy = torch.softmax(torch.arange(6, dtype=torch.float64).expand(BATCH, 6), -1)
    return {"value": model(obs[1], hidden, policy).value.reshape(-1).detach()}


REFERENCES: dict[str, Callable[[], dict[str, torch.Tensor]]] = {
    **{f"step_fp32/{m}": (lambda m=m: _renamed(run_forward(m), "forward", "step_fp32")) for m in RECURRENT},
    **{f"replay/{m}": (lambda m=m: reference_replay(m)) for m in REPLAYED},
    **{
        f"fast_{o}/{m}": (lambda m=m, o=o: reference_fast(m, o))
        for o in ("second", "first")
        for m in ADAPTIVE
    },
    **{f"test_time/{m}": (lambda m=m: reference_test_time(m)) for m in ADAPTIVE},
    **{f"value/{m}": (lambda m=m: reference_value(m)) for m in RECURRENT},
}
#: What has no reference here: the plain forward itself, and the bf16 variants (rounded to 8 bits).
RECORDED = [case for case in CASES if case not in REFERENCES]


def record() -> None:
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        torch.save({case: CASES[case]() for case in RECORDED}, GOLDEN)
    finally:
        torch.set_num_threads(previous)


@cache
def _golden() -> dict[str, dict[str, torch.Tensor]]:
    return torch.load(GOLDEN)


@pytest.mark.parametrize("case", list(REFERENCES))
def test_variant_equals_its_plain_computation_here(case: str, single_torch_thread) -> None:
    """In float64 the variants differ from the plain computation by summation order alone."""
    expected = REFERENCES[case]()
    got = CASES[case]()
    assert sorted(got) == sorted(expected)
    for key, value in expected.items():
        torch.testing.assert_close(got[key], value, rtol=1e-9, atol=1e-12, msg=lambda m, k=key: f"{k}: {m}")


@pytest.mark.parametrize("case", RECORDED)
def test_variant_reproduces_the_recorded_outputs_and_gradients(case: str, single_torch_thread) -> None:
    expected = _golden()[case]
    got = CASES[case]()
    assert sorted(got) == sorted(expected)
    for key, value in expected.items():
        exact = EXACT or not value.is_floating_point()
        rtol, atol = (0.0, 0.0) if exact else TOLERANCE[value.dtype]
        torch.testing.assert_close(got[key], value, rtol=rtol, atol=atol, msg=lambda m, k=key: f"{k}: {m}")


if __name__ == "__main__" and "--record" in sys.argv:
    record()
