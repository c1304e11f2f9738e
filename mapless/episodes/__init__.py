"""Episodes: the training sampler (as the references sample) and fixed evaluation sets."""

from mapless.episodes.episode import Episode

__all__ = ["Episode"]
