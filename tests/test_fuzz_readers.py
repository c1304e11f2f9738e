"""Fuzz test of every reader of user files: episode pickles and JSON, offline scene folders,
scene cache files, checkpoints and configs. Each gets damaged copies of a valid file (one-byte flips,
truncations, values of the wrong kind anywhere in its structure) and crafted files (allocation and
nesting bombs, foreign classes); every one must be read or refused with the reader's clear error
(a MaplessError; for a cache file, StaleCacheError, which means "rebuild"), never another exception,
a crash or a hang. The seed is fixed, so a failure names an input that reproduces it."""

from __future__ import annotations

import gzip
import json
import pickle
import signal
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from damage import one_byte_flips
from scene_fixtures import grid_scene
from train_fixtures import tiny_config

from mapless import checkpoint as ckpt
from mapless.config import load_config, to_dict
from mapless.configs import configs_dir
from mapless.episodes import evalsets
from mapless.errors import MaplessError
from mapless.experiments.config import ExperimentConfig
from mapless.models import build_model
from mapless.offline import export_scene, import_episode_file, load_offline_scene
from mapless.sim import cache
from mapless.sim.config import SimConfig
from mapless.sim.episode import Episode
from mapless.train.config import TrainConfig, stored_train_config
from mapless.train.run import resume_config

SEED = 25
SECONDS_PER_INPUT = 10.0
REPO = Path(__file__).resolve().parents[1]
SAMPLE = Path(__file__).parent / "data" / "hoz_bathroom_val_22_sample.pkl"
#: Values of every kind, put where a file expects something else.
JUNK: tuple[Any, ...] = (
    None, True, 0, -1, 2**70, 1e308, float("nan"), float("-inf"), "", "x|y|z", "FloorPlan1",
    [], {}, [[1, 2], [3]], {"a": [None]}, [1.5] * 5, "0.00|0.00|0|0",
)  # fmt: skip


class Hang(BaseException):
    """Raised by the alarm: a BaseException, so that no reader's ``except Exception`` swallows it."""


def _alarm(signum: int, frame: Any) -> None:
    raise Hang


def outcome(read: Callable[[], Any], clean: type[BaseException] = MaplessError) -> str:
    """ "read" or "refused"; anything else (another exception, a hang) fails the test."""
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, SECONDS_PER_INPUT)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            read()
        return "read"
    except clean:
        return "refused"
    except Hang:
        pytest.fail(f"no answer within {SECONDS_PER_INPUT} s")
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def fuzz(path: Path, read: Callable[[], Any], inputs: Iterator[str], clean: type = MaplessError) -> dict:
    """Run ``read`` once per damaged version of ``path`` (each input writes it and yields a label);
    returns how many were read and refused."""
    counts = {"read": 0, "refused": 0}
    for label in inputs:
        try:
            counts[outcome(read, clean)] += 1
        except BaseException as error:
            raise AssertionError(f"{path.name}, input {label}: {type(error).__name__}: {error}") from error
    return counts


def byte_damage(path: Path, count: int, seed: int = SEED) -> Iterator[str]:
    """One-byte flips (all bits, then single bits) and truncations of ``path``; restored after."""
    good = path.read_bytes()
    yield from (f"flip@{o}" for o in one_byte_flips(path, count, seed))
    yield from (f"bit@{o}" for o in one_byte_flips(path, count // 2, seed + 1, mask=0x10))
    try:
        for cut in np.random.default_rng(seed).integers(0, len(good), count // 4):
            path.write_bytes(good[:cut])
            yield f"cut@{cut}"
    finally:
        path.write_bytes(good)


def mutated(value: Any, rng: np.random.Generator) -> Any:
    """``value`` (parsed JSON/YAML) with one node, chosen at random, replaced, dropped or wrapped."""
    if isinstance(value, dict) and value and rng.random() < 0.8:
        key = list(value)[rng.integers(len(value))]
        copy = dict(value)
        if rng.random() < 0.15:
            del copy[key]
        else:
            copy[key] = mutated(value[key], rng)
        return copy
    if isinstance(value, list) and value and rng.random() < 0.8:
        i = int(rng.integers(len(value)))
        return [*value[:i], mutated(value[i], rng), *value[i + 1 :]]
    if rng.random() < 0.1:
        return [value]
    return JUNK[rng.integers(len(JUNK))]


def structure_damage(
    path: Path, count: int, load: Callable, dump: Callable, seed: int = SEED
) -> Iterator[str]:
    """``count`` versions of the structured file ``path``, each with one node :func:`mutated`."""
    good = path.read_bytes()
    data = load(good)
    rng = np.random.default_rng(seed)
    try:
        for i in range(count):
            path.write_bytes(dump(mutated(data, rng)))
            yield f"mutation {i}"
    finally:
        path.write_bytes(good)


def json_bytes(value: Any) -> bytes:
    return json.dumps(value).encode()  # NaN and Infinity included, as Python's json reads them


def written(path: Path, contents: list[bytes]) -> Iterator[str]:
    for i, data in enumerate(contents):
        path.write_bytes(data)
        yield f"crafted {i}"


# ---------------------------------------------------------------------------------- episode pickles


class Foreign:
    """A class the reader does not know: it becomes an inert placeholder."""

    def __init__(self, **fields: Any):
        self.__dict__.update(fields)


def _shared(depth: int) -> list:
    nested: list = []
    for _ in range(depth):
        nested = [nested, nested]
    return nested


def _cyclic() -> list:
    loop: list = []
    loop.append(loop)
    return [loop]


def crafted_pickles(rng: np.random.Generator) -> list[bytes]:
    entry = {"scene": "FloorPlan1", "goal_object_type": "Mug", "task_data": [], "state": "0.00|0.00|0|0"}
    fields = [*entry, "glove_embedding", "room"]
    bombs = [
        b"\x80\x02]r\xff\xff\xff\x7f.",  # a memo index of 2**31: an 8 GiB memo table
        b"\x80\x02]h\x05.",  # a memo read never stored
        b"c__builtin__\nbytearray\n(I10000000000\ntR.",  # 10 GB of zeros
        b"cbuiltins\nlist\n(cbuiltins\nrange\n(I1000000000000\ntRtR.",
        b"\x80\x04\x95\xff\xff\xff\xff\x00\x00\x00\x00.",  # a frame longer than the file
        b"\x80\x02X\xff\xff\xff\x7fabc.",  # a string longer than the file
        b"\x80\x02" + b"]" * 50_000 + b"a" * 49_999 + b".",  # nested 50 000 deep
        b"c_codecs\nencode\n(X\x01\x00\x00\x00aX\x0b\x00\x00\x00no-such-codectR.",
        pickle.dumps(_shared(60)),  # 2**60 paths through 60 shared lists
        pickle.dumps(_cyclic()),
        pickle.dumps([Foreign(x=Foreign(x=1))] * 3),
        pickle.dumps([{**entry, "state": Foreign(x=1e400, z=0, rotation=0, horizon=0)}]),
        pickle.dumps([{**entry, "glove_embedding": torch.ones(3, dtype=torch.bfloat16)}]),
        pickle.dumps([{**entry, "glove_embedding": [10**400]}]),
        pickle.dumps(
            [{**entry, "task_data": ["Mug|1|2|3"] * 3, "state": Foreign(x=1, z=2, rotation=90, horizon=0)}]
        ),
        b"",
    ]
    entries = [
        pickle.dumps([{**entry, **{k: JUNK[rng.integers(len(JUNK))] for k in rng.choice(fields, 2)}}])
        for _ in range(40)
    ]
    return bombs + entries


def test_episode_pickles(tmp_path):
    path = tmp_path / "episodes.pkl"
    path.write_bytes(SAMPLE.read_bytes())

    def read() -> None:
        import_episode_file(path)  # reading, then mapping onto the built-in scenes

    inputs = [byte_damage(path, 60), written(path, crafted_pickles(np.random.default_rng(SEED)))]
    counts = fuzz(path, read, (label for each in inputs for label in each))
    assert counts["refused"] > 30 and sum(counts.values()) > 150


# ------------------------------------------------------------------------------- arrangement files


def test_arrangement_files(tmp_path):
    """The rearrangement dataset's pickles (``env.layouts.source``, ``mapless scenes variants``)."""
    from mapless.scenes import arrangements

    def pose(name: str, x: float) -> dict:
        return {"name": name, "objectName": name, "position": {"x": x, "y": 0.9, "z": 0.5},
                "rotation": {"x": 0.0, "y": 90.0, "z": 0.0}}  # fmt: skip

    episode = {
        "target_poses": [pose("Mug_1", 1.0), pose("Apple_2", -0.5)],
        "starting_poses": [pose("Mug_1", 0.25), pose("Apple_2", 0.0)],
        "openable_data": [{"name": "Fridge_1", "start_openness": 0.0, "target_openness": 1.0}],
    }
    data = {"FloorPlan1": [episode, episode]}
    packed, plain = tmp_path / "a.pkl.gz", tmp_path / "a.pkl"
    packed.write_bytes(gzip.compress(pickle.dumps(data)))
    plain.write_bytes(pickle.dumps(data))

    def reader(path: Path) -> Callable[[], None]:
        def read() -> None:
            arrangements._read.cache_clear()  # keyed by size and mtime, which a rewrite may keep
            for phase in arrangements.PHASES:
                arrangement = arrangements.arrangement_of(str(path), "FloorPlan1", 1, phase)
                numbers = [v for p in arrangement.poses for v in (*p.position, *p.rotation)]
                assert all(np.isfinite(numbers)), "a non-finite pose was read"

        return read

    flips = fuzz(packed, reader(packed), byte_damage(packed, 40))
    bombs = crafted_pickles(np.random.default_rng(SEED))[:10]
    inputs = [structure_damage(plain, 120, pickle.loads, pickle.dumps), written(plain, bombs)]
    counts = fuzz(plain, reader(plain), (label for each in inputs for label in each))
    # The gzip CRC refuses nearly every flip; most mutations break the format, the rest are read
    # as finite poses (checked in read).
    assert flips["refused"] >= 0.9 * sum(flips.values()) and counts["refused"] >= 80


# ------------------------------------------------------------------------------------ episode JSON


def test_episode_json(tmp_path):
    episodes = [
        Episode("FloorPlan21", "Apple", (0.5, -1.25, 90, 0), 7, ("Apple|+1|+2|+3",), "val/kitchen/000"),
        Episode("FloorPlan221", "Laptop", (1.0, 2.0, 270, 30), 12, (), "val/living_room/000"),
    ]
    data = evalsets.dumps(episodes, "val", "mjolnir22", 0, "0" * 16)
    packed, plain = tmp_path / "set.json.gz", tmp_path / "set.json"
    packed.write_bytes(data)
    plain.write_bytes(gzip.decompress(data))
    counts = fuzz(packed, lambda: evalsets.load(packed), byte_damage(packed, 40))
    counts2 = fuzz(plain, lambda: evalsets.load(plain), structure_damage(plain, 120, json.loads, json_bytes))
    crafted = [b"[" * 100_000, b'{"format": "mapless-episodes/1", "episodes": ' + b"[" * 50_000, b"\xff\xfe"]
    counts3 = fuzz(plain, lambda: evalsets.load(plain), written(plain, crafted))
    assert counts["refused"] > 20 and counts2["refused"] > 60 and counts3["refused"] == 3


# ---------------------------------------------------------------------------------- offline folders


@pytest.fixture(scope="module")
def scene():
    return grid_scene()


@pytest.mark.parametrize(
    "name", ["graph.json", "grid.json", "visible_object_map.json", "objects_bb.json", "mapless.json"]
)
def test_offline_scene_json(scene, tmp_path, name):
    folder = export_scene(scene, tmp_path, "mjolnir")
    path = folder / name
    inputs = [structure_damage(path, 40, json.loads, json_bytes), written(path, [b"[" * 100_000, b"\xff"])]
    counts = fuzz(path, lambda: load_offline_scene(folder), (label for each in inputs for label in each))
    assert counts["refused"] > 10


def test_offline_scene_features(scene, tmp_path):
    folder = export_scene(scene, tmp_path, "mjolnir")
    path = folder / "resnet18_featuremap.hdf5"
    good = path.read_bytes()
    rng = np.random.default_rng(SEED)

    def header_flips() -> Iterator[str]:  # the metadata (superblock, B-trees, heaps) is up front
        try:
            for _ in range(50):
                damaged = bytearray(good)
                offset = int(rng.integers(0, 8192))
                damaged[offset] ^= int(rng.integers(1, 256))
                path.write_bytes(bytes(damaged))
                yield f"flip@{offset}"
            for cut in (0, 100, 4096, len(good) // 2):
                path.write_bytes(good[:cut])
                yield f"cut@{cut}"
        finally:
            path.write_bytes(good)

    counts = fuzz(path, lambda: load_offline_scene(folder), header_flips())
    assert counts["refused"] > 10


# --------------------------------------------------------------------------------------- scene cache

SCENE = "FloorPlan425"
FAST = SimConfig(ray_resolution=14)


def test_scene_cache_files(tmp_path):
    cache.load_or_build(SCENE, FAST, tmp_path)
    path = cache.cache_path(SCENE, FAST, tmp_path)
    original = cache.load(path, FAST)
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    header = json.loads(str(arrays.pop("header")))
    rng = np.random.default_rng(SEED)

    def read() -> None:
        """Refused (the scene is rebuilt), or read as the scene that was written: never another one."""
        data = cache.load(path, FAST)
        for name in cache._ARRAY_FIELDS:
            assert np.array_equal(getattr(data, name), getattr(original, name)), f"{name} read damaged"
        for name in ("scene", "room_type", "instance_ids", "instance_types", "feature_scale"):
            assert getattr(data, name) == getattr(original, name), f"{name} read damaged"

    def crafted(part: str) -> Iterator[str]:
        """Headers or arrays of the wrong kind, with a checksum made to match."""
        good = path.read_bytes()
        try:
            for i in range(30):
                head, arrs = dict(header), dict(arrays)
                if part == "header":
                    head = mutated(head, rng)
                else:
                    name = cache._ARRAY_FIELDS[i % len(cache._ARRAY_FIELDS)]
                    replacement = (
                        np.zeros(()),
                        arrs[name][:-1],
                        arrs[name][::-1].astype(np.float64) * 1000,
                        np.array(["a"]),
                    )
                    arrs[name] = replacement[i % 4]
                if isinstance(head, dict):
                    head["checksum"] = cache._checksum(arrs)
                with path.open("wb") as handle:
                    np.savez(handle, header=np.array(json.dumps(head)), **arrs)
                yield f"crafted {part} {i}"
        finally:
            path.write_bytes(good)

    flips = fuzz(path, read, byte_damage(path, 30), clean=cache.StaleCacheError)
    headers = fuzz(path, read, crafted("header"), clean=cache.StaleCacheError)
    arrays_ = fuzz(path, read, crafted("arrays"), clean=cache.StaleCacheError)
    # Counted, so that a reader that starts accepting damage fails here: the zip's CRCs and the
    # checksum catch byte damage, and every array replacement breaks a shape, a kind or an index.
    assert flips["refused"] >= 0.9 * sum(flips.values()) and sum(flips.values()) > 45
    assert arrays_ == {"read": 0, "refused": 30}
    # A header mutation is read only where it changed nothing the simulator uses (meta, or the
    # checksum, which is made to match again).
    assert headers["refused"] >= 20
    read()  # the original is back and valid


# --------------------------------------------------------------------------------------- checkpoints


def test_checkpoints(tmp_path):
    config = tiny_config("a3c")
    weights = build_model(config.model).state_dict()
    model_file = tmp_path / "model.pt"
    payload = ckpt.model_payload(weights, config, {"episodes": 4, "frames": 20})
    ckpt.atomic_save(payload, model_file)
    rng = np.random.default_rng(SEED)

    def read() -> None:
        """What ``mapless eval`` reads (the whole config, then the model): refused, or loaded with the
        weights and counters that were written, never other ones."""
        stored_train_config(ckpt.load_file(model_file)["config"])
        model, _, counters = ckpt.load_model(model_file)
        for name, value in model.state_dict().items():
            assert torch.equal(value, weights[name]), f"{name} read damaged"
        assert all(isinstance(v, int) for v in counters.values())

    read()  # the undamaged file loads

    def crafted(part: str, count: int) -> Iterator[str]:
        """Well-formed files (a valid digest) whose content is wrong in one place."""
        names = list(weights)
        for i in range(count):
            bad = dict(payload)
            if part == "config":
                bad["config"] = mutated(to_dict(config), rng)
            elif part == "structure":
                bad[["format", "kind", "config", "model", "counters"][i % 5]] = JUNK[i % len(JUNK)]
            elif part == "weights":
                model = dict(weights)
                name = names[i % len(names)]
                model[name] = (torch.zeros(3), torch.zeros(()), "weights", None, torch.zeros(2, 2))[i % 5]
                if i % 3 == 0:
                    del model[name]
                bad["model"] = model
            elif part == "non-finite":  # a diverged model, saved with a valid digest
                name = names[i % len(names)]
                bad["model"] = {
                    **weights,
                    name: torch.full_like(weights[name], (float("nan"), float("inf"))[i % 2]),
                }
            else:
                bad["counters"] = mutated(payload["counters"], rng)
            ckpt.atomic_save(bad, model_file)
            yield f"crafted {part} {i}"

    def foreign() -> Iterator[str]:
        for i, value in enumerate(([1, 2], "text", {"format": 1}, torch.zeros(3))):
            torch.save(value, model_file)
            yield f"foreign {i}"

    counts = {part: fuzz(model_file, read, crafted(part, 15)) for part in ("config", "structure", "weights",
                                                                           "non-finite", "counters")}  # fmt: skip
    counts["foreign"] = fuzz(model_file, read, foreign())
    ckpt.atomic_save(payload, model_file)
    flips = fuzz(model_file, read, byte_damage(model_file, 30))
    # Counted, so that a reader that starts accepting damage fails here. A mutated config or counter
    # may still be a valid one (read, with the weights intact); nothing else may be read.
    for part in ("structure", "weights", "non-finite"):
        assert counts[part] == {"read": 0, "refused": 15}, part
    assert counts["foreign"] == {"read": 0, "refused": 4}
    assert counts["config"]["refused"] >= 8 and counts["counters"]["refused"] >= 10
    assert flips["refused"] >= 0.9 * sum(flips.values()) and sum(flips.values()) > 45

    run = tmp_path / "run"
    state = {**payload, "kind": "checkpoint", "optimizer": {"state": {}, "param_groups": []}, "rng": []}
    ckpt.atomic_save(state, run / ckpt.CHECKPOINT_FILE)
    resumed = resume_config(run)[1]

    def resume() -> None:
        assert ckpt.digest(resume_config(run)[1]) == ckpt.digest(resumed), "read damaged"

    flips = fuzz(run / ckpt.CHECKPOINT_FILE, resume, byte_damage(run / ckpt.CHECKPOINT_FILE, 20))
    assert flips["refused"] >= 0.9 * sum(flips.values()) and sum(flips.values()) > 30


# ------------------------------------------------------------------------------------------- configs

#: A billion laughs: 4**12 leaves reached through aliases of aliases.
LAUGHS = b"l0: &l0 [x, x]\n" + b"".join(
    b"l%d: &l%d [*l%d, *l%d, *l%d, *l%d]\n" % (i + 1, i + 1, i, i, i, i) for i in range(12)
)
CRAFTED_YAML = [
    b"[" * 100_000,
    LAUGHS,
    b"model: " + LAUGHS.replace(b"\n", b"\n  ").rstrip() + b"\n",
    b"seed: !!python/object/apply:os.system ['echo hacked']\n",
    b"\tseed: 1\n",
    b"seed: 1e400\n",
    b"- 1\n- 2\n",
    b"",
    b"\x00\x01\x02",
    b"? [1, 2]\n: 3\n",
    b"model: {name: a3c, hidden_size: 1e400}\n",
    b"env: {sim: {horizons: [0, 1e400]}}\n",
    b"1: 2\nseed: 3\n",
]


@pytest.mark.parametrize(
    ("kind", "source"),
    [(TrainConfig, "train_smoke.yaml"), (ExperimentConfig, "table3_smoke.yaml")],
    ids=["train", "experiment"],
)
def test_configs(tmp_path, kind, source):
    path = tmp_path / "config.yaml"
    path.write_bytes((configs_dir() / source).read_bytes())
    load_config(kind, path)

    def dump(value: Any) -> bytes:
        return yaml.safe_dump(value).encode()

    inputs = [
        byte_damage(path, 40),
        structure_damage(path, 60, yaml.safe_load, dump),
        written(path, CRAFTED_YAML),
    ]
    counts = fuzz(path, lambda: load_config(kind, path), (label for each in inputs for label in each))
    assert counts["refused"] > 40
    for override in ("seed", "=1", "a..b=1", ".=1", "seed=[", "model=3", "model.name.x=1", "env.sim=[1]"):
        path.write_bytes((configs_dir() / source).read_bytes())
        assert outcome(lambda o=override: load_config(kind, path, [o])) in ("read", "refused")
