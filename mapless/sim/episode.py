"""The navigation episode: where it starts, what it looks for, and how long the best path is."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Episode:
    """One ObjectNav episode.

    ``start`` is the pose ``(x, z, yaw, horizon)``. ``optimal_length`` counts actions including the
    final ``Done`` (SAVN's ``len(path)``), so ``optimal_length >= 5`` is the papers' ``L>=5``
    subset; -1 when unknown. ``target_ids`` restricts success to those instances (SAVN's
    ``task_data``); empty means any instance of ``target``.
    """

    scene: str
    target: str
    start: tuple[float, float, int, int]
    optimal_length: int = -1
    target_ids: tuple[str, ...] = ()
    episode_id: str = ""

    def to_dict(self) -> dict:
        d = asdict(self)
        d["start"] = list(self.start)
        d["target_ids"] = list(self.target_ids)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Episode:
        x, z, yaw, horizon = d["start"]
        return cls(
            scene=d["scene"],
            target=d["target"],
            start=(float(x), float(z), int(yaw), int(horizon)),
            optimal_length=int(d.get("optimal_length", -1)),
            target_ids=tuple(d.get("target_ids", ())),
            episode_id=str(d.get("episode_id", "")),
        )
