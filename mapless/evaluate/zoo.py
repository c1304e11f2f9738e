"""Shipped agents and their results (the zoo): ``<root>/<experiment>/<model>/`` holds a chosen
agent's weights at half precision (``model.pt``, a model file :func:`mapless.checkpoint.load_model`
reads back into float32), its per-episode results with the episodes they were played on
(``results.json.gz``) and a manifest of where they come from (``manifest.json``). A results-only
entry (a row of an experiment report, every seed of it; :func:`report_entries`) has no ``model.pt``:
``mapless compare`` reads it, ``mapless eval`` cannot run it.

The root is the package's ``data/zoo`` folder, or ``$MAPLESS_ZOO`` (tests, a maintainer's working
copy). Entries are named ``zoo:<experiment>/<model>`` wherever a command accepts a model or results.
Half precision halves the weights; an entry is only written when the half-precision weights score
inside the float32 result's 95 % bootstrap interval on the same episodes (:func:`half_precision_check`).
"""

from __future__ import annotations

import gzip
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

import mapless.data
from mapless.checkpoint import atomic_save
from mapless.errors import MaplessError
from mapless.evaluate.episode_sets import episodes_digest
from mapless.evaluate.metrics import EpisodeResult, aggregate
from mapless.evaluate.stats import seed_estimates
from mapless.files import unwritable, write_bytes
from mapless.sim.episode import Episode

PREFIX = "zoo:"
ROOT_VARIABLE = "MAPLESS_ZOO"
MODEL_FILE = "model.pt"
RESULTS_FILE = "results.json.gz"
MANIFEST_FILE = "manifest.json"
#: The most the package's zoo may hold, weights and results together.
MAX_BYTES = 40 * 2**20


class ZooError(MaplessError):
    pass


def zoo_root(root: str | Path | None = None) -> Path:
    """``root``, else ``$MAPLESS_ZOO``, else the package's ``data/zoo`` folder."""
    if root is not None:
        return Path(root)
    if os.environ.get(ROOT_VARIABLE):
        return Path(os.environ[ROOT_VARIABLE])
    return Path(mapless.data.__file__).parent / "zoo"


def is_zoo(spec: str | Path) -> bool:
    return str(spec).startswith(PREFIX)


@dataclass(frozen=True, order=True)
class ZooEntry:
    experiment: str
    model: str
    folder: Path

    @property
    def name(self) -> str:
        return f"{PREFIX}{self.experiment}/{self.model}"

    @property
    def has_weights(self) -> bool:
        return (self.folder / MODEL_FILE).is_file()

    @property
    def model_file(self) -> Path:
        """The shipped weights; an error for a results-only entry."""
        if not self.has_weights:
            raise ZooError(
                f"{self.name} ships per-episode results only, no weights: compare with it "
                f"(mapless compare RUN {self.name}); the entries with weights: "
                f"{', '.join(e.name for e in entries(self.folder.parent.parent) if e.has_weights) or 'none'}"
            )
        return self.folder / MODEL_FILE

    @property
    def manifest(self) -> dict:
        try:
            return json.loads((self.folder / MANIFEST_FILE).read_text())
        except (OSError, ValueError) as error:
            raise ZooError(f"{self.name}: cannot read its manifest ({error})") from None

    def stored(self) -> dict:
        """The results file: ``episodes`` (each seed's per-episode results) and ``episode_set`` (the
        episodes they were played on), checked against the manifest's digest."""
        path = self.folder / RESULTS_FILE
        try:
            data = json.loads(gzip.decompress(path.read_bytes()))
        except (OSError, ValueError, EOFError) as error:
            raise ZooError(f"{self.name}: cannot read its results {path.name} ({error})") from None
        digest = episodes_digest([Episode.from_dict(e) for e in data.get("episode_set", [])])
        if digest != self.manifest.get("episodes", {}).get("digest"):
            raise ZooError(f"{self.name}: its results' episodes do not match the digest of its manifest")
        return data

    def results(self) -> list[list[EpisodeResult]]:
        return [[EpisodeResult.from_dict(d) for d in seed] for seed in self.stored()["episodes"]]

    def episodes(self) -> list[Episode]:
        return [Episode.from_dict(e) for e in self.stored()["episode_set"]]


def entries(root: str | Path | None = None) -> list[ZooEntry]:
    """Every entry under the root (a folder with a manifest), by experiment and model."""
    base = zoo_root(root)
    found = base.glob(f"*/*/{MANIFEST_FILE}") if base.is_dir() else []
    return sorted(ZooEntry(p.parent.parent.name, p.parent.name, p.parent) for p in found)


def entry(spec: str, root: str | Path | None = None) -> ZooEntry:
    """The entry ``zoo:<experiment>/<model>``; a name the zoo lacks is an error naming those it has."""
    name = str(spec).removeprefix(PREFIX)
    experiment, _, model = name.partition("/")
    for found in entries(root):
        if (found.experiment, found.model) == (experiment, model):
            return found
    known = ", ".join(e.name for e in entries(root)) or "none: the zoo is empty"
    raise ZooError(f"no zoo entry {PREFIX}{name} (zoo:<experiment>/<model>); the zoo has {known}")


def listing(root: str | Path | None = None) -> str:
    """A markdown table of the entries: SR and SPL with their intervals (over episodes and seeds),
    episodes, seeds, whether weights ship, the commits that trained and added them; or a line saying
    there are none."""
    rows = []
    for e in entries(root):
        m = e.manifest
        sr, spl = m.get("success", {}), m.get("spl", {})
        rows.append(
            f"| {e.name} | {_pct(sr)} | {_pct(spl)} | {m.get('episodes', {}).get('count', '?')} "
            f"| {sr.get('seeds', '?')} | {'yes' if e.has_weights else 'results only'} "
            f"| {_trained_at(m)} | {_short(m.get('added_commit'))} |"
        )
    if not rows:
        return f"no entries in the zoo ({zoo_root(root)})"
    head = (
        "| entry | SR | SPL | episodes | seeds | weights | trained at | added at |\n"
        "|---|---|---|---|---|---|---|---|"
    )
    return "\n".join([head, *rows])


def _pct(estimate: dict) -> str:
    if "mean" not in estimate:
        return "–"
    return f"{100 * estimate['mean']:.1f} [{100 * estimate['ci_low']:.1f}, {100 * estimate['ci_high']:.1f}]"


def _short(commit: str | None) -> str:
    return commit[:12] if commit else "unknown"


def _trained_at(manifest: dict) -> str:
    # A row of no runs (random) was never trained: "unknown" would read as lost provenance.
    if "runs" in manifest and not manifest["runs"]:
        return "untrained"
    return _short(manifest.get("training_commit"))


def half_precision(weights: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The float32/float64 tensors of a state dict as float16 (loading copies them back into the
    model's float32 parameters); integer buffers as they are."""
    return {
        k: v.to(torch.float16) if v.dtype in (torch.float32, torch.float64) else v for k, v in weights.items()
    }


def success_interval(results: Sequence[EpisodeResult]) -> tuple[float, float, float]:
    """SR of a result set and its 95 % bootstrap interval over episodes."""
    estimate = seed_estimates([results])["success"]
    return estimate.mean, estimate.ci_low, estimate.ci_high


def half_precision_check(full: Sequence[EpisodeResult], half: Sequence[EpisodeResult]) -> dict:
    """SR of the float32 and the half-precision weights on the same episodes; an error when the
    latter leaves the former's 95 % interval (the shipped weights would not be the row's agent)."""
    sr, low, high = success_interval(full)
    half_sr = float(aggregate(half)["success"])
    check = {"float32_sr": sr, "float32_ci": [low, high], "float16_sr": half_sr}
    if not low <= half_sr <= high:
        raise ZooError(
            f"the half-precision weights score SR {100 * half_sr:.1f} %, outside the float32 SR "
            f"{100 * sr:.1f} % [{100 * low:.1f}, {100 * high:.1f}] on the same {len(full)} episodes; "
            "nothing was added"
        )
    return check


def writable_entry(
    experiment: str, model: str, *, with_weights: bool, root: str | Path | None = None
) -> Path:
    """The folder the entry ``<experiment>/<model>`` would be written to; an error, before any
    evaluation is spent on it, when the name is not one entry's, when a results-only entry would drop
    shipped weights, or when the folder cannot be written (an installed package's zoo: set
    $MAPLESS_ZOO)."""
    if "/" in experiment or "/" in model or not experiment or not model:
        raise ZooError(f"an entry is named <experiment>/<model>; got {experiment!r} and {model!r}")
    folder = zoo_root(root) / experiment / model
    if not with_weights and (folder / MODEL_FILE).is_file():
        raise ZooError(
            f"{PREFIX}{experiment}/{model} ships weights, which a results-only entry of that name would "
            "drop; name the results another experiment (e.g. <experiment>-seeds); nothing was added"
        )
    if (why := unwritable(folder, (MODEL_FILE, RESULTS_FILE, MANIFEST_FILE))) is not None:
        raise ZooError(f"cannot add {PREFIX}{experiment}/{model}: {why} (${ROOT_VARIABLE} names another zoo)")
    return folder


def write_entry(
    experiment: str,
    model: str,
    payload: dict | None,
    results: Sequence[Sequence[EpisodeResult]],
    episodes: Sequence[Episode],
    manifest: dict,
    root: str | Path | None = None,
) -> ZooEntry:
    """Write an entry: the model file ``payload`` (weights already at half precision; None: a
    results-only entry), each seed's results with their episodes (compact JSON, gzip without a
    timestamp, so the bytes depend on the content only) and the manifest, which gains the episode
    digest and SR/SPL with their intervals."""
    folder = writable_entry(experiment, model, with_weights=payload is not None, root=root)
    keys = set_keys(episodes)
    for seed in results:
        if (mismatch := key_mismatch(result_keys(seed), keys)) is not None:
            raise ZooError(f"{experiment}/{model}: results not on the entry's episodes ({mismatch})")
    folder.mkdir(parents=True, exist_ok=True)
    if payload is not None:
        atomic_save(payload, folder / MODEL_FILE)
    stored = {
        "episodes": [[r.to_dict() for r in seed] for seed in results],
        "episode_set": [e.to_dict() for e in episodes],
    }
    text = json.dumps(stored, separators=(",", ":")).encode()
    write_bytes(folder / RESULTS_FILE, gzip.compress(text, compresslevel=9, mtime=0))
    estimates = {k: v.to_dict() for k, v in seed_estimates(results).items() if k in ("success", "spl")}
    manifest = {
        **manifest,
        "experiment": experiment,
        "model": model,
        **estimates,
        "episodes": {
            **manifest.get("episodes", {}),
            "count": len(episodes),
            "digest": episodes_digest(episodes),
        },
    }
    write_bytes(folder / MANIFEST_FILE, (json.dumps(manifest, indent=1) + "\n").encode())
    return ZooEntry(experiment, model, folder)


def result_keys(results: Sequence[EpisodeResult]) -> list[tuple]:
    """What identifies the episodes of a result set, in index order: index, scene, target, id."""
    return [(r.index, r.scene, r.target, r.episode_id) for r in sorted(results, key=lambda r: r.index)]


def set_keys(episodes: Sequence[Episode]) -> list[tuple]:
    """:func:`result_keys` of the results an episode list would give."""
    return [(i, e.scene, e.target, e.episode_id) for i, e in enumerate(episodes)]


def key_mismatch(a: list[tuple], b: list[tuple]) -> str | None:
    """Where two lists of :func:`result_keys` part (their lengths, or the first episode that differs),
    or None: pairing results by index is only meaningful on one and the same episode list."""
    if len(a) != len(b):
        return f"{len(a)} episodes against {len(b)}"
    for x, y in zip(a, b, strict=True):
        if x != y:
            return f"episode {x[0]} is {x[1]}/{x[2]} ({x[3]!r}) on one side, {y[1]}/{y[2]} ({y[3]!r}) on the other"
    return None


def folder_size(root: str | Path | None = None) -> int:
    """Bytes of every file under the root."""
    base = zoo_root(root)
    return sum(p.stat().st_size for p in base.rglob("*") if p.is_file()) if base.is_dir() else 0
