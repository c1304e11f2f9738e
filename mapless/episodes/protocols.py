"""Evaluation protocols: which success rule, which floor plans and which episodes a number is measured on.

* ``standard`` (the default; SAVN's ``full_eval.py`` selection): success within 1.0 m, the paper's
  stated rule; select on ``val`` (x21-x25), report once on ``test`` (x26-x30); the evaluation sets
  never start with the target in view.
* ``paper`` (what the paper and MJOLNIR did): the same rule and sets, but select *and* report on the
  same x21-x30 episodes, an optimistic estimate; every report made with it says so.
* ``reference`` (what the SAVN/MJOLNIR/HOZ published numbers were measured under): success within
  1.5 m, AI2-THOR's default ``visibilityDistance``, which the references' offline data follow;
  select on the odd floor plans x21-x29 (``ref_val``), report once on the even ones x22-x30
  (``ref_test``), the split of the published pickles; a start may already see the target, as in
  the published files. Its sets are the published episodes themselves by default: the HOZ line's
  22-class val and test files (shipped in the package and mapped onto the built-in scenes as
  ``ref_val_hoz22`` / ``ref_test_hoz22``, docs/guide/interop.md), so its runs train on their classes,
  target set ``hoz22``. A run trained on another target set is scored on that set's sets
  (mapless.episodes.evalsets.set_path): ``mjolnir22`` (the paper's targets) on the project's
  sampled sets ``ref_val_mjolnir22`` / ``ref_test_mjolnir22``. A set of targets the run never
  trained for is refused by an experiment and flagged by ``mapless eval``.

Training is the same under every protocol (x01-x20) except for the success rule, which also decides
the reward and ``Done``, and the default target set (``Protocol.target_set``, the classes of the
protocol's episodes): a run trained for the reference protocol uses ``visibility_distance`` 1.5 and,
unless its configuration names another, the published episodes' classes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

from mapless.errors import UnknownNameError
from mapless.sim.config import SimConfig


@dataclass(frozen=True)
class Protocol:
    """select_split / report_split: evaluation-set splits (``mapless.scenes.catalogue.SPLITS``);
    equal when selection and report share their episodes. visible_starts: the protocol's evaluation
    sets may start with the target already in view. No protocol's sampled sets start on a pose-graph
    island (``SceneData.usable_poses``). Which set of a split is read follows the model's training
    target set (mapless.episodes.evalsets.set_path); target_set: the training target set of a run
    trained for this protocol whose configuration names none, that of the protocol's own sets."""

    name: str
    select_split: str
    report_split: str
    visibility_distance: float
    visible_starts: bool
    label: str
    target_set: str = "mjolnir22"

    def sim(self, config: SimConfig) -> SimConfig:
        """``config`` with this protocol's success rule."""
        return dataclasses.replace(config, visibility_distance=self.visibility_distance)

    def train_overrides(self, config: Mapping | None = None) -> list[str]:
        """TrainConfig overrides (``KEY=VALUE``) that train a run for this protocol: its success rule
        and its episodes' classes, unless the TrainConfig mapping ``config`` names a target set."""
        rule = [f"env.sim.visibility_distance={self.visibility_distance}"]
        named = "target_set" in ((config or {}).get("env") or {})
        return rule + ([] if named else [f"env.target_set={self.target_set}"])


PROTOCOLS: dict[str, Protocol] = {
    "standard": Protocol(
        "standard", "val", "test", 1.0, False,
        "selected on val (x21-x25), reported once on test (x26-x30); success within 1.0 m",
    ),
    "paper": Protocol(
        "paper", "paper", "paper", 1.0, False,
        "PAPER PROTOCOL: selected and reported on the same x21-x30 episodes (optimistic, as in the "
        "paper/MJOLNIR); success within 1.0 m",
    ),
    "reference": Protocol(
        "reference", "ref_val", "ref_test", 1.5, True,
        "REFERENCE PROTOCOL (the SAVN/MJOLNIR/HOZ data's): success within 1.5 m, selected on val (odd "
        "x21-x29), reported once on test (even x22-x30), starts may see the target", "hoz22",
    ),
}  # fmt: skip


def get_protocol(name: str) -> Protocol:
    if name not in PROTOCOLS:
        raise UnknownNameError("protocol", name, PROTOCOLS)
    return PROTOCOLS[name]


def protocol_of_split(split: str) -> Protocol:
    """The protocol whose evaluation sets a split's set belongs to (its success rule and start rule)."""
    for protocol in PROTOCOLS.values():
        if split in (protocol.select_split, protocol.report_split):
            return protocol
    raise UnknownNameError(
        "evaluation split", split, [s for p in PROTOCOLS.values() for s in (p.select_split, p.report_split)]
    )


#: The episode sets a command's ``--split`` names: the protocol's selection and report sets, and the
#: paper protocol's one set (x21-x30), which selects and reports alike.
SPLIT_ROLES = ("val", "test", "paper")


def split_for(protocol: str, role: str) -> str:
    """The evaluation-set split that ``role`` (``val``: selection, ``test``: report, ``paper``: the
    paper protocol's set) uses under ``protocol``; ``mapless eval --protocol reference --split test``
    reads ``ref_test``."""
    p = get_protocol(protocol)
    if role not in SPLIT_ROLES:
        raise UnknownNameError("split", role, SPLIT_ROLES)
    return {"val": p.select_split, "test": p.report_split, "paper": "paper"}[role]
