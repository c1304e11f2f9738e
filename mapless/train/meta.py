"""SAVN's meta-learning inner loop, batched over episodes with per-episode fast weights.

Within an episode, after every k interaction steps (k = 6, at most 4 times; never after the step that
ends the episode) the adapted parameters θ take one SGD step on the learned interaction loss:

    θ_{i+1} = θ_i - α ∇_θ L_int^φ(rows_i; θ_i),   rows_i = the last k rows [h_t || π_t] (acted with θ_i)

and the outer loss is the A3C loss of the whole episode, each step evaluated with the θ_i that acted
(the paper's eq. 3/5). Batching: every episode b owns its fast weights θ^b (a ``[B, ...]`` tensor per
adapted parameter, starting as a broadcast view of θ_0); the forward pass is
``vmap(functional_call(model, θ^b, ...))``. Because episode b's interaction loss depends only on θ^b,
one ``autograd.grad`` of Σ_b L_int^b w.r.t. the batched θ gives every episode's own gradient.

Meta-gradients (:meth:`InnerLoop.backward`):

* ``second_order`` (default, SAVN): backpropagate the outer loss through every inner step
  (``create_graph=True``); θ_0 receives ``Π(I - α H_int) ∇L_nav`` terms and φ receives gradient only
  through the inner steps.
* ``first_order`` (the first-order Taylor form, eq. 4: L_nav(θ) - α <∇L_int^φ(θ), ∇L_nav(θ)>): the
  fast weights follow the same trajectory but the inner step is a constant shift for θ_0 (its gradient
  is the sum of the outer loss's partial derivatives w.r.t. every θ_i), and φ receives the gradient of
  the inner-product term, ``-α Σ_i (∂g_i/∂φ)ᵀ v_i`` with ``v_i = ∂L_nav/∂θ_{i+1}`` held constant. For a
  single inner step this differs from second order only by ``-α H_int v`` on θ_0 (the φ gradients are
  equal); tests/test_meta.py checks exactly that.

At test time (``meta_train=False``) the same inner steps run with φ frozen and no graph is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor
from torch.func import functional_call, vmap

from mapless.models.base import ModelOutput, NavModel


@dataclass
class InnerLoopState:
    """Per-batch state of one lockstep rollout of B episodes (create with :meth:`InnerLoop.start`)."""

    fast: dict[str, Tensor]
    rows: list[Tensor] = field(default_factory=list)
    updates: int = 0
    #: first order only: (inner gradients g_i, fast weights θ_{i+1}) of every inner step.
    records: list[tuple[dict[str, Tensor], dict[str, Tensor]]] = field(default_factory=list)


class InnerLoop:
    """Functional, batched SAVN inner loop around an adaptive model (savn, gve, spatt, cvmeta).

    Usage per lockstep batch of episodes::

        loop = InnerLoop(model)
        state = loop.start(batch_size)
        for t in range(T):
            out = loop.forward(state, obs, hidden, prev_policy)
            ...  # sample actions, step the environments
            loop.observe(state, out, alive)  # alive [B] bool: episode not ended by this step
        loop.backward(state, a3c_loss(...).total.sum())
    """

    def __init__(
        self,
        model: NavModel,
        inner_lr: float | None = None,
        max_updates: int | None = None,
        first_order: bool = False,
        meta_train: bool = True,
    ):
        if not model.adaptive:
            raise TypeError(f"model {model.config.name!r} has no learned interaction loss")
        self.model = model
        self.inner_lr = model.inner_lr if inner_lr is None else inner_lr
        # k is fixed by the model: it is the TCN's input-channel count.
        self.steps = model.config.interaction_steps
        self.max_updates = model.config.max_inner_updates if max_updates is None else max_updates
        self.first_order = first_order
        self.meta_train = meta_train
        self.names = model.inner_parameter_names()

    def start(self, batch_size: int) -> InnerLoopState:
        params = dict(self.model.named_parameters())
        fast = {}
        for name in self.names:
            p = params[name]
            if self.meta_train:
                # A broadcast view: differentiable back to θ_0, no copy until the first update.
                fast[name] = p.unsqueeze(0).expand(batch_size, *p.shape)
            else:
                fast[name] = p.detach().unsqueeze(0).expand(batch_size, *p.shape).clone().requires_grad_()
        return InnerLoopState(fast=fast)

    def forward(
        self,
        state: InnerLoopState,
        obs: dict[str, Tensor],
        hidden: tuple[Tensor, Tensor],
        prev_policy: Tensor,
    ) -> ModelOutput:
        """The model's forward pass with each episode's own fast weights."""
        model = self.model

        def one_episode(fast, episode_obs, h, c, policy):
            single = {key: value.unsqueeze(0) for key, value in episode_obs.items()}
            out = functional_call(
                model, fast, (single, (h.unsqueeze(0), c.unsqueeze(0)), policy.unsqueeze(0))
            )
            return out.logits[0], out.value[0], out.hidden[0][0], out.hidden[1][0]

        logits, value, h, c = vmap(one_episode, randomness="different")(
            state.fast, obs, hidden[0], hidden[1], prev_policy
        )
        return ModelOutput(logits, value, (h, c))

    def observe(self, state: InnerLoopState, output: ModelOutput, alive: Tensor) -> bool:
        """Record the step's row ``[h_t || π_t]``; after k rows take the inner step for the episodes
        still running. Returns True when an inner step was taken."""
        state.rows.append(torch.cat([output.hidden[0], torch.softmax(output.logits, dim=-1)], dim=-1))
        if len(state.rows) < self.steps:
            return False
        rows = torch.stack(state.rows, dim=1)
        state.rows = []  # SAVN resets the learned-loss buffer after every chunk of k
        if state.updates >= self.max_updates or not bool(alive.any()):
            return False
        self.adapt(state, rows, alive)
        return True

    def adapt(self, state: InnerLoopState, rows: Tensor, active: Tensor) -> None:
        """One inner SGD step of the episodes where ``active`` (``[B]`` bool) on ``rows [B, k, H+6]``."""
        loss = (self.model.learned_loss(rows) * active.to(rows.dtype)).sum()
        names = list(state.fast)
        keep_graph = self.meta_train  # second order needs it; first order needs g_i's graph to φ
        grads = torch.autograd.grad(
            loss, [state.fast[n] for n in names], create_graph=keep_graph, allow_unused=True
        )
        new_fast, used = {}, {}
        for name, g in zip(names, grads, strict=True):
            w = state.fast[name]
            if g is None:  # parameter outside the learned loss's reach: unchanged (SAVN)
                new_fast[name] = w
                continue
            if not self.meta_train:
                new_fast[name] = (w - self.inner_lr * g).detach().requires_grad_()
            elif self.first_order:
                new_fast[name] = w - self.inner_lr * g.detach()
                used[name] = g
            else:
                new_fast[name] = w - self.inner_lr * g
        if self.meta_train and self.first_order:
            state.records.append((used, {n: new_fast[n] for n in used}))
        state.fast = new_fast
        state.updates += 1

    def backward(self, state: InnerLoopState, loss: Tensor) -> None:
        """Accumulate the meta-gradient of the outer ``loss`` (a scalar) into ``.grad`` of θ_0 and φ."""
        if not self.meta_train:
            raise RuntimeError("backward() needs an InnerLoop built with meta_train=True")
        if not self.first_order:
            loss.backward()
            return
        params = [(n, p) for n, p in self.model.named_parameters() if p.requires_grad]
        phi = set(self.model.learned_loss_parameter_names())
        theta = [(n, p) for n, p in params if n not in phi]
        shifted = [t for _, after in state.records for t in after.values()]
        grads = torch.autograd.grad(
            loss, [p for _, p in theta] + shifted, retain_graph=bool(state.records), allow_unused=True
        )
        _accumulate([p for _, p in theta], grads[: len(theta)])
        if not state.records:
            return
        # Eq. 4's inner-product term: only φ is differentiated (θ_0's share is the dropped Hessian term).
        v = iter(grads[len(theta) :])
        inner = loss.new_zeros(())
        for used, _after in state.records:
            for g in used.values():
                vi = next(v)
                if vi is not None:
                    inner = inner + (g * vi.detach()).sum()
        phi_params = [p for n, p in params if n in phi]
        if inner.requires_grad:
            phi_grads = torch.autograd.grad(-self.inner_lr * inner, phi_params, allow_unused=True)
            _accumulate(phi_params, phi_grads)


def _accumulate(params: list[Tensor], grads: tuple[Tensor | None, ...]) -> None:
    for p, g in zip(params, grads, strict=True):
        if g is None:
            continue
        p.grad = g.detach().clone() if p.grad is None else p.grad + g.detach()
