"""The navigation episode: where it starts, what it looks for, and how long the best path is."""

from __future__ import annotations

import math
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
        """The episode of a JSON mapping (:meth:`to_dict`); a malformed one is a ``ValueError``
        that says which field is wrong (episode files are user input)."""
        if not isinstance(d, dict):
            raise ValueError(f"an episode must be a mapping, not {type(d).__name__}")
        missing = [k for k in ("scene", "target", "start") if k not in d]
        if missing:
            raise ValueError(f"episode has no {', '.join(missing)}")
        for key in ("scene", "target", "episode_id"):
            if not isinstance(d.get(key, ""), str):
                raise ValueError(f"episode {key} {d[key]!r} is not a string")
        start = d["start"]
        if not (
            isinstance(start, list | tuple)
            and len(start) == 4
            and all(_number(v) and math.isfinite(v) for v in start)
            and all(float(v).is_integer() for v in start[2:])
        ):
            raise ValueError(f"episode start {start!r} is not [x, z, yaw, horizon] (yaw, horizon whole)")
        target_ids = d.get("target_ids", [])
        if not (isinstance(target_ids, list | tuple) and all(isinstance(t, str) for t in target_ids)):
            raise ValueError(f"episode target_ids {target_ids!r} is not a list of object ids")
        optimal = d.get("optimal_length", -1)
        if not (_number(optimal) and float(optimal).is_integer()):
            raise ValueError(f"episode optimal_length {optimal!r} is not an integer")
        x, z, yaw, horizon = start
        return cls(
            scene=d["scene"],
            target=d["target"],
            start=(float(x), float(z), int(yaw), int(horizon)),
            optimal_length=int(optimal),
            target_ids=tuple(target_ids),
            episode_id=d.get("episode_id", ""),
        )


def _number(value: object) -> bool:
    # bool is an int subclass, but true/false in a pose is a malformed file, not 1/0
    return isinstance(value, int | float) and not isinstance(value, bool)
