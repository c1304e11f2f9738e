"""``mlp``: a small recurrent policy over the context vectors, a sanity baseline (not one of the
paper's models). It shows what the observations alone support at a fraction of the cost.

Inputs (docs/guide/simulator.md, "Observations"): the context rows of every category flattened (C x 4), the GloVe
cosine of every category to the target (C), and the target's own context row (4, zeros when the
target is not a category), plus the previous policy (6). Two 256-wide ReLU layers, an LSTMCell (``model.hidden_size``,
512 as every model), actor and critic on h.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mapless.knowledge import Knowledge
from mapless.models.base import NUM_ACTIONS, RECURRENT_CORE_ROLES, ModelConfig, RecurrentNavModel
from mapless.models.layers import target_row, target_similarity
from mapless.models.roles import ParameterRoles
from mapless.models.settings import RECURRENT

WIDTH = 256


class MlpModel(RecurrentNavModel):
    description = "sanity baseline: MLP over the context rows + target row + GloVe cosines -> LSTM"
    parameter_roles = RECURRENT_CORE_ROLES | ParameterRoles(encoder=("layer1", "layer2"))
    settings = RECURRENT

    def __init__(self, config: ModelConfig, knowledge: Knowledge | None = None):
        super().__init__(config, knowledge)
        c = self.num_categories
        self.register_buffer("all_glove", torch.tensor(self.knowledge.glove, dtype=torch.float32))
        self.layer1 = nn.Linear(c * 4 + c + 4 + NUM_ACTIONS, WIDTH)
        self.layer2 = nn.Linear(WIDTH, WIDTH)
        self.build_recurrent_core(WIDTH, glorot=False)

    def encode(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        context = obs["context"]
        similarity = target_similarity(obs["target_embedding"], self.all_glove)
        own = target_row(context, obs["target_index"])
        x = torch.cat([context.flatten(1), similarity, own, prev_policy], dim=1)
        return F.relu(self.layer2(F.relu(self.layer1(x)))), None
