"""The references' ``SharedAdam`` update rule (dgriff777/rl_a3c_pytorch, used by SAVN and MJOLNIR).

It differs from ``torch.optim.Adam(amsgrad=True)`` in where ε enters: the references divide by
``sqrt(max v) + ε`` and fold both bias corrections into the step size (``lr·sqrt(1-β2^t)/(1-β1^t)``),
whereas torch divides by ``sqrt(max v)/sqrt(1-β2^t) + ε``. With the references' large ε = 1e-3 the
two differ noticeably in early steps, so both trainers use this rule. State is created eagerly so
that it can be moved to shared memory before the Hogwild workers start.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch
from torch import Tensor

from mapless.agent.buffers import BufferPool
from mapless.train.config import A3CConfig


class SharedAdam(torch.optim.Optimizer):
    def __init__(
        self,
        params: Iterable[Tensor],
        lr: float = 1e-4,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-3,
        amsgrad: bool = True,
    ):
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps, "amsgrad": amsgrad})
        for group in self.param_groups:
            for p in group["params"]:
                state = self.state[p]
                state["step"] = torch.zeros((), dtype=torch.float64)
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                if amsgrad:
                    state["max_exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        # Not optimizer state (never saved or shared): the step's √v + ε, in the same memory every step.
        self._scratch = BufferPool()

    @classmethod
    def from_config(cls, params: Iterable[Tensor], config: A3CConfig) -> SharedAdam:
        return cls(
            params, lr=config.lr, betas=(config.beta1, config.beta2), eps=config.eps, amsgrad=config.amsgrad
        )

    def share_memory(self) -> SharedAdam:
        for state in self.state.values():
            for value in state.values():
                value.share_memory_()
        return self

    @torch.no_grad()
    def step(self, closure=None):
        loss = closure() if closure is not None else None
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                grad = p.grad
                state["step"] += 1  # in place: shared between Hogwild workers
                t = float(state["step"])
                state["exp_avg"].mul_(beta1).add_(grad, alpha=1 - beta1)
                state["exp_avg_sq"].mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                second = state["exp_avg_sq"]
                if group["amsgrad"]:
                    second = torch.maximum(state["max_exp_avg_sq"], second, out=state["max_exp_avg_sq"])
                denom = self._scratch.get(f"denom.{id(p)}", p.shape, p.dtype, p.device)
                torch.sqrt(second, out=denom).add_(group["eps"])
                step_size = group["lr"] * math.sqrt(1 - beta2**t) / (1 - beta1**t)
                p.addcdiv_(state["exp_avg"], denom, value=-step_size)
        return loss
