"""The acting layer's sampling rule, which training and evaluation share."""

from __future__ import annotations

import numpy as np
import torch

from mapless.agent.acting import policy_probabilities, sample_actions


def test_inverse_cdf_sampling_by_hand() -> None:
    probs = np.array([[0.1, 0.2, 0.3, 0.4, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]], dtype=np.float32)
    # CDF of row 0: 0.1, 0.3, 0.6, 1.0, 1.0, 1.0; an action is the number of CDF entries <= u.
    for u, expected in [(0.0, 0), (0.05, 0), (0.1, 1), (0.29, 1), (0.31, 2), (0.61, 3), (0.999999, 3)]:
        assert sample_actions(probs[:1], np.array([u]))[0] == expected, u
    # A row's action depends on its own number only, and a certain action is always taken.
    both = sample_actions(probs, np.array([0.31, 0.0]))
    assert both.tolist() == [2, 5]
    assert sample_actions(probs[1:], np.array([0.999999]))[0] == 5


def test_rounding_never_picks_an_action_past_the_last_likely_one() -> None:
    # float32 probabilities that sum to a hair below 1: u close to 1 must still pick action 3.
    probs = np.array([[0.3, 0.3, 0.1, 0.3 - 1e-7, 0.0, 0.0]], dtype=np.float32)
    assert sample_actions(probs, np.array([1.0 - 1e-12]))[0] == 3


def test_the_law_is_the_policy() -> None:
    logits = torch.tensor([[0.5, -1.0, 2.0, 0.0, 1.0, -2.0]])
    probs = policy_probabilities(logits)
    assert np.allclose(probs, torch.softmax(logits, -1).numpy())
    rng = np.random.default_rng(0)
    draws = sample_actions(np.repeat(probs, 200_000, axis=0), rng.random(200_000))
    frequencies = np.bincount(draws, minlength=6) / len(draws)
    assert np.allclose(frequencies, probs[0], atol=0.004)
