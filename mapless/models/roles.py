"""Parameter roles: what the meta-learning inner loop does with each of a model's parameters.

Every model declares, as :attr:`NavModel.parameter_roles <mapless.models.base.NavModel>`, which of
its top-level submodules (or parameters) play which role; every trainable parameter must fall under
exactly one, which :func:`assign_roles` checks when the model is built. The inner loop
(:mod:`mapless.agent.meta`) reads the roles, never a parameter's spelling: a layer named
``cell_proj`` is adapted like any other policy layer.

* ``policy``: θ of the paper's eq. 1 (the fusion, the previous-action embedding, LSTM, actor),
  adapted by every inner step;
* ``encoder``: the state and target encoders v, u, adapted only under ``adapt: all`` (SAVN's rule);
* ``outer_only``: trained by the outer loss alone because the learned loss cannot reach them (the
  critic, the references' dead modules, GVE's graph, which feeds only the critic): SAVN "adapts"
  them with a None gradient, i.e. leaves them unchanged;
* ``learned_loss``: φ, the learned interaction loss, never adapted; the outer loss trains it through
  the inner steps.

Non-adaptive models declare the same roles: they document the model's structure, and the model
becomes adaptive by adding a learned loss, nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from torch import nn

from mapless.errors import MaplessError

POLICY, ENCODER, OUTER_ONLY, LEARNED_LOSS = "policy", "encoder", "outer_only", "learned_loss"


class ParameterRoleError(MaplessError):
    """A model's trainable parameter has no role, or more than one."""


@dataclass(frozen=True)
class ParameterRoles:
    """Per role, the names of top-level submodules or parameters in it (a submodule's name covers every
    parameter under it: ``lstm`` covers ``lstm.weight_ih``). Names a model does not build (optional
    modules such as the references' dead ones) are allowed. ``a | b`` joins two declarations."""

    policy: tuple[str, ...] = ()
    encoder: tuple[str, ...] = ()
    outer_only: tuple[str, ...] = ()
    learned_loss: tuple[str, ...] = ()

    def __or__(self, other: ParameterRoles) -> ParameterRoles:
        return ParameterRoles(
            **{f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self)}
        )

    def roles_of(self, parameter: str) -> list[str]:
        """Every role whose names cover ``parameter`` (a dotted parameter name)."""
        return [
            f.name
            for f in fields(self)
            if any(parameter == n or parameter.startswith(n + ".") for n in getattr(self, f.name))
        ]


def assign_roles(model: nn.Module, roles: ParameterRoles) -> dict[str, str]:
    """``{trainable parameter name: role}``; raises :class:`ParameterRoleError` naming every trainable
    parameter with no role or with several (frozen parameters need none)."""
    assigned, problems = {}, []
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue
        found = roles.roles_of(name)
        if len(found) == 1:
            assigned[name] = found[0]
        elif not found:
            problems.append(f"{name!r} has no role")
        else:
            problems.append(f"{name!r} has several roles ({', '.join(found)})")
    if problems:
        raise ParameterRoleError(
            f"model {type(model).__name__}: {'; '.join(problems)}. Every trainable parameter needs "
            f"exactly one role in parameter_roles ({POLICY}, {ENCODER}, {OUTER_ONLY} or "
            f"{LEARNED_LOSS}; see docs/guide/models.md, 'Adding a model')"
        )
    return assigned
