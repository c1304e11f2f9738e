"""Episodes: the training sampler (as the references sample) and fixed evaluation sets."""

from mapless.sim.episode import Episode

__all__ = ["Episode"]
