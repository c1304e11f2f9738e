"""Acting with a policy: which observation keys a model reads, numpy observations to tensors, what a
recurrent policy carries from step to step, reproducible action sampling, and acting with test-time
adaptation. Shared by training (both algorithms) and evaluation."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from mapless.models.base import NUM_ACTIONS, ModelOutput, NavModel
from mapless.observations import OBSERVATION_KEYS, ObservationSizes, zeros


class PolicyMemory:
    """What a recurrent policy carries from one step to the next, per slot: the LSTM state ``(h, c)``
    and the previous step's policy (an input of every model, as in SAVN). Zero at an episode's start.

    Every update is out of place, so a graph through an earlier step (training, test-time
    adaptation) keeps the values it was built with."""

    def __init__(self, model: NavModel, batch_size: int, device: torch.device | None = None):
        self.hidden: tuple[Tensor, Tensor] = model.initial_state(batch_size, device)
        self.prev_policy: Tensor = torch.zeros(batch_size, NUM_ACTIONS, device=device)

    def reset(self, slots: Tensor) -> None:
        """New episodes in ``slots``."""
        self.hidden = (self.hidden[0].index_fill(0, slots, 0.0), self.hidden[1].index_fill(0, slots, 0.0))
        self.prev_policy = self.prev_policy.index_fill(0, slots, 0.0)

    def keep(self, rows: Tensor) -> None:
        """Only ``rows`` go on (the others' episodes ended)."""
        self.hidden = (self.hidden[0].index_select(0, rows), self.hidden[1].index_select(0, rows))
        self.prev_policy = self.prev_policy.index_select(0, rows)

    def advance(self, output: ModelOutput) -> Tensor:
        """Carry ``output``'s state to the next step (in float32 whatever the compute dtype) and
        return its policy. The next step differentiates into this one through whatever of
        ``output`` the caller did not detach."""
        self.hidden = (output.hidden[0].float(), output.hidden[1].float())
        self.prev_policy = torch.softmax(output.logits.float(), dim=-1)
        return self.prev_policy


class _RecordingObs(dict):
    """A dict that remembers which keys were read."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.read: set[str] = set()

    def __getitem__(self, key: str):
        self.read.add(key)
        return super().__getitem__(key)


def observation_keys(model: NavModel) -> tuple[str, ...]:
    """The observation keys ``model`` reads, found by one probe forward pass on zeros.

    Gathering the 7x7 feature map is the costliest part of a batched environment step, and several
    models (cvmeta, mjolnir_o) never read it, so the environment is asked only for what is used.
    """
    sizes = ObservationSizes(model.num_categories, model.feature_channels, model.glove_dim)
    device = next((p.device for p in model.parameters()), torch.device("cpu"))
    probe = _RecordingObs({k: v.to(device) for k, v in zeros(sizes).items()})
    was_training = model.training
    model.eval()
    with torch.no_grad():
        model(probe, model.initial_state(1, device), torch.zeros(1, NUM_ACTIONS, device=device))
    model.train(was_training)
    return tuple(k for k in OBSERVATION_KEYS if k in probe.read)


def to_tensors(obs: dict[str, np.ndarray], device: torch.device, batch: bool = True) -> dict[str, Tensor]:
    """Numpy observations -> tensors on ``device`` (``batch=False`` adds the batch dimension)."""
    out = {}
    for key, value in obs.items():
        array = np.asarray(value)
        if not array.flags.writeable:  # NavEnv hands out read-only views of cached arrays
            array = array.copy()
        tensor = torch.from_numpy(array)
        out[key] = (tensor if batch else tensor.unsqueeze(0)).to(device, non_blocking=True)
    return out


def sample_actions(probabilities: np.ndarray, uniforms: np.ndarray) -> np.ndarray:
    """Inverse-CDF samples of the policies ``probabilities [B, A]``, one uniform number in [0, 1) per
    row: the law of ``multinomial``, but each episode's actions depend only on its own numbers,
    whatever else shares the batch. Training and evaluation both act through it. The CDF is summed in
    float64 and the number scaled to its last entry, so rounding never selects a zero-probability
    action past the end."""
    cdf = np.cumsum(probabilities, axis=1, dtype=np.float64)
    u = np.asarray(uniforms, dtype=np.float64) * cdf[:, -1]
    return np.minimum((cdf <= u[:, None]).sum(axis=1), probabilities.shape[1] - 1)


def policy_probabilities(logits: Tensor) -> np.ndarray:
    """``softmax(logits)`` as the numpy array :func:`sample_actions` takes."""
    return torch.softmax(logits.detach(), dim=-1).cpu().numpy()


class AdaptingActor:
    """Acting with SAVN's inner loop at its test-time setting: every slot's fast weights adapt in
    place on the learned interaction loss (:class:`~mapless.agent.meta.TestTimeAdaptation`)
    while θ and φ stay fixed. The evaluator's adaptive agent and PPO's whole-episode collection act
    through it."""

    def __init__(self, model: NavModel, batch_size: int):
        from mapless.agent.meta import TestTimeAdaptation

        self.loop = TestTimeAdaptation(model)
        # θ stays fixed while acting; only the per-episode fast copies take inner gradients.
        self.frozen = [p for p in model.parameters() if p.requires_grad]
        for p in self.frozen:
            p.requires_grad_(False)
        self.state = self.loop.start(batch_size)

    @property
    def steps(self) -> int:
        """k: the interaction steps between two inner updates."""
        return self.loop.steps

    @property
    def updates(self) -> np.ndarray:
        """Inner steps taken by each slot's current episode."""
        return self.state.slot_updates.numpy()

    def reset_slots(self, slots: Tensor) -> None:
        """New episodes in ``slots``: their fast weights back to θ."""
        self.loop.reset_slots(self.state, slots)

    def forward(
        self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor
    ) -> ModelOutput:
        return self.loop.forward(self.state, obs, hidden, prev_policy)

    def value(self, obs: dict[str, Tensor], hidden: tuple[Tensor, Tensor], prev_policy: Tensor) -> Tensor:
        """``[B]`` V of the current state under each slot's fast weights; records nothing."""
        return self.loop.value(self.state, obs, hidden, prev_policy)

    def observe(self, output: ModelOutput, alive: Tensor) -> None:
        """After a step: every k steps the slots still running (and under their update limit) adapt."""
        self.loop.observe(self.state, output, alive)

    def close(self) -> None:
        """θ trainable again (training resumes after acting)."""
        for p in self.frozen:
            p.requires_grad_(True)
