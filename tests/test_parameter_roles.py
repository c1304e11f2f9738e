"""Parameter roles: the inner loop adapts what a model declares, whatever its layers are called, and a
model whose trainable parameter has no role (or several) is refused when built, naming it."""

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapless.agent.meta import TestTimeAdaptation
from mapless.knowledge import synthetic_knowledge
from mapless.models import build_model, registry
from mapless.models.base import NUM_ACTIONS, RECURRENT_CORE_ROLES, RecurrentNavModel
from mapless.models.layers import target_row
from mapless.models.learned_loss import LEARNED_LOSS_ROLES, LearnedLossMixin
from mapless.models.roles import ParameterRoleError, ParameterRoles
from mapless.models.synthetic import synthetic_observations

K = 2  # interaction steps per inner update


class CellProjModel(LearnedLossMixin, RecurrentNavModel):
    """Layer names containing "ll" (``cell_proj``, ``small_mlp``), which a rule on names would freeze."""

    default_inner_lr = 0.1
    parameter_roles = (
        RECURRENT_CORE_ROLES
        | LEARNED_LOSS_ROLES
        | ParameterRoles(encoder=("small_mlp",), policy=("cell_proj",))
    )

    def __init__(self, config, knowledge=None):
        super().__init__(config, knowledge)
        self.small_mlp = nn.Linear(4, 8)
        self.cell_proj = nn.Linear(8 + NUM_ACTIONS, 8)
        self.lstm = nn.LSTMCell(8, self.hidden_size)
        self.actor_linear = nn.Linear(self.hidden_size, NUM_ACTIONS)
        self.critic_linear = nn.Linear(self.hidden_size, 1)
        self._build_learned_loss(with_key_linear=False)

    def encode(self, obs: dict[str, Tensor], hidden, prev_policy: Tensor):
        row = F.relu(self.small_mlp(target_row(obs["context"], obs["target_index"])))
        return torch.tanh(self.cell_proj(torch.cat([row, prev_policy], dim=1))), None


class UnassignedModel(CellProjModel):
    def __init__(self, config, knowledge=None):
        super().__init__(config, knowledge)
        self.extra_gate = nn.Linear(8, 8)


class TwiceAssignedModel(CellProjModel):
    parameter_roles = CellProjModel.parameter_roles | ParameterRoles(outer_only=("cell_proj",))


@pytest.fixture
def build(monkeypatch):
    knowledge = synthetic_knowledge(6, 300, seed=0)

    def build(model_class, **overrides):
        monkeypatch.setitem(registry.MODELS, "roles_example", model_class)
        torch.manual_seed(0)
        return build_model(
            "roles_example", knowledge=knowledge, hidden_size=16, interaction_steps=K, **overrides
        )

    return build


def test_a_layer_named_cell_proj_is_adapted_by_the_inner_loop(build) -> None:
    model = build(CellProjModel, adapt="policy")
    names = model.inner_parameter_names()
    assert {"cell_proj.weight", "cell_proj.bias", "lstm.weight_ih", "actor_linear.weight"} <= set(names)
    assert not any(n.startswith(("small_mlp", "critic_linear", "ll_")) for n in names)
    assert "small_mlp.weight" in build(CellProjModel, adapt="all").inner_parameter_names()
    assert set(model.learned_loss_parameter_names()) == {
        n for n, _ in model.named_parameters() if n.startswith("ll_tc.")
    }

    loop = TestTimeAdaptation(model)  # fast weights change in place
    state = loop.start(2)
    obs = synthetic_observations(2, model.knowledge)
    hidden, policy = model.initial_state(2), torch.zeros(2, NUM_ACTIONS)
    for _ in range(K):
        out = loop.forward(state, obs, hidden, policy)
        hidden, policy = out.hidden, torch.softmax(out.logits, -1)
        loop.observe(state, out, torch.ones(2, dtype=torch.bool))
    assert int(state.slot_updates.min()) == 1
    assert not torch.allclose(state.fast["cell_proj.weight"][0], model.cell_proj.weight)
    assert "small_mlp.weight" not in state.fast


def test_a_parameter_without_a_role_is_refused_by_name(build) -> None:
    with pytest.raises(ParameterRoleError, match=r"'extra_gate\.weight' has no role") as error:
        build(UnassignedModel)
    assert "extra_gate.bias" in str(error.value) and "UnassignedModel" in str(error.value)
    with pytest.raises(
        ParameterRoleError, match=r"'cell_proj\.weight' has several roles \(policy, outer_only\)"
    ):
        build(TwiceAssignedModel)


def test_every_registered_model_gives_each_trainable_parameter_one_role() -> None:
    for name in registry.model_names():
        for extras in (False, True):
            model = build_model(name, reference_extras=extras, feature_channels=8)
            trainable = [n for n, p in model.named_parameters() if p.requires_grad]
            assert list(model.parameter_role_map()) == trainable, name
