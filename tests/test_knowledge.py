"""Packaged priors: GloVe tables, category graphs, parent lists and the parent reward."""

import json
import pathlib
import re
from importlib import resources

import numpy as np
import pytest

from mapless.errors import UnknownNameError
from mapless.knowledge import (
    category_glove,
    glove_vector,
    hierarchical_adjacency,
    normalize_adjacency,
    parent_lists,
    parent_reward,
    parent_reward_by_name,
    parent_weights,
    parents_of,
    vg_adjacency,
)
from mapless.knowledge.graph import GRAPH_TARGET_SETS, training_cooccurrence
from mapless.knowledge.parents import build_parent_lists
from mapless.scenes.catalogue import ROOM_TYPES, scene_names
from mapless.scenes.categories import all_targets, category_set, targets
from mapless.scenes.layout import load_scene

REPO = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = REPO / "mapless"
TESTS = REPO / "tests"

#: The team's data folder beside the repository, however it is spelled (joined at run time, so that
#: this file does not name it itself).
SHARED_SPELLINGS = (
    "/".join(("..", "shared")),
    "/".join(("", "work", "shared")),
    str(REPO.parent.joinpath("shared")),
)
#: A quoted absolute, home or parent-relative path: whatever a test reads lives in the repository.
OUTSIDE_PATH_LITERAL = re.compile(r"""["'`](?:/|~/|\.\./)\w""")
#: ``Path(__file__)`` climbed with ``.parent`` / ``.parents[n]`` (counted against the file's depth).
FILE_CLIMB = re.compile(
    r"__file__\)(?:\.resolve\(\))?((?:\.parent\b)*)(?:\.parents\[(\d+)\])?((?:\.parent\b)*)"
)


def test_glove_tables_and_renamed_types():
    assert category_glove("mjolnir101").shape == (101, 300)
    assert category_glove("all_types").shape == (117, 300)
    # MJOLNIR's thorv1 vectors (reference-implementations §1.8 fingerprint).
    assert np.allclose(glove_vector("Box")[:4], [0.42701, -0.09343, 0.1823, -0.04091], atol=1e-5)
    for v5, v1 in [
        ("DiningTable", "TableTop"),
        ("CoffeeTable", "TableTop"),
        ("SideTable", "NightStand"),
        ("Bottle", "Glassbottle"),
    ]:
        assert np.array_equal(glove_vector(v5), glove_vector(v1))
    assert not np.allclose(glove_vector("Box", "all_types"), glove_vector("Box"))
    for target in all_targets("mjolnir22") + all_targets("savn") + all_targets("hoz22"):
        assert glove_vector(target).shape == (300,)
        assert glove_vector(target, "all_types").shape == (300,)
    names = category_set().names
    assert np.array_equal(category_glove()[names.index("TableTop")], glove_vector("DiningTable"))
    with pytest.raises(UnknownNameError, match="Television"):
        glove_vector("Televison")


def test_visual_genome_prior_matches_the_documented_graph():
    a = vg_adjacency()
    assert a.shape == (101, 101)
    assert int(a.sum()) == 614 and int(np.trace(a)) == 54 and int((a.sum(1) == 0).sum()) == 22


def test_hierarchical_graph_is_purified_vg_plus_parent_edges():
    h = hierarchical_adjacency() > 0
    vg = vg_adjacency() > 0
    names = category_set().names
    assert (h == h.T).all() and h.diagonal().all()
    parent_edges = np.zeros_like(h)
    for room in ROOM_TYPES:
        graph_targets = {t for name in GRAPH_TARGET_SETS for t in targets(name)[room]}
        for target, entries in parent_lists()[room].items():
            if target not in graph_targets:  # a later target set's lists pay the reward only
                continue
            for e in entries:
                i, j = names.index(target), names.index(e["parent"])
                assert h[i, j] and h[j, i]
                parent_edges[i, j] = parent_edges[j, i] = True
    purified = (vg | vg.T) & training_cooccurrence()
    expected = purified | parent_edges | np.eye(len(names), dtype=bool)
    assert (h == expected).all()
    assert (purified.sum() < (vg | vg.T).sum()) and parent_edges.sum() > 0
    # Dropping the kitchen's relationships removes kitchen-only parent edges (the paper's ablation).
    no_kitchen = hierarchical_adjacency(rooms=("living_room", "bedroom", "bathroom")) > 0
    i, j = names.index("Toaster"), names.index("StoveBurner")
    assert h[i, j] and not no_kitchen[i, j] and not purified[i, j]


def test_normalize_adjacency_by_hand():
    a = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    # Row sums 2, 1, 0 -> d = [1/√2, 1, 0]; result = D Aᵀ D.
    expected = np.array([[0.5, 0.0, 0.0], [1 / np.sqrt(2), 1.0, 0.0], [0.0, 0.0, 0.0]])
    assert np.allclose(normalize_adjacency(a), expected)


def test_shipped_parent_lists_equal_a_rebuild_from_training_scenes():
    shipped = json.loads(resources.files("mapless.data").joinpath("priors/parents.json").read_text())
    for set_name in ("mjolnir101", "all_types"):
        assert shipped[set_name] == build_parent_lists(set_name)


def test_parent_lists_are_larger_training_objects():
    names = set(category_set().names)
    train = [load_scene(s) for s in scene_names("train")]
    types = category_set().type_to_index
    pickupable = {
        category_set().names[types[o.type]]
        for s in train
        for o in s.objects
        if o.pickupable and o.type in types
    }
    for room in ROOM_TYPES:
        for target, entries in parent_lists()[room].items():
            for e in entries:
                assert e["parent"] in names and e["parent"] not in pickupable and e["parent"] != target
                assert 0 < e["p"] <= 1
    # The paper's example: Drawer is a parent object in living rooms and bathrooms.
    assert any("Drawer" in parents_of("living_room", t) for t in parent_lists()["living_room"])
    assert any("Drawer" in parents_of("bathroom", t) for t in parent_lists()["bathroom"])
    assert parents_of("bedroom", "Pillow")["Bed"] == 1.0


def test_parent_reward_first_sighting_per_episode():
    weights = np.array([0.0, 0.6, 0.3, 0.0], dtype=np.float32)
    seen = np.zeros(4, dtype=bool)
    view = np.array([True, True, True, False])
    bonus, seen1 = parent_reward(view, weights, seen)
    assert bonus == pytest.approx(0.6) and seen1.tolist() == [False, True, False, False]
    assert not seen.any()  # input untouched
    bonus, seen2 = parent_reward(view, weights, seen1)  # the other parent pays next
    assert bonus == pytest.approx(0.3) and seen2.tolist() == [False, True, True, False]
    bonus, seen3 = parent_reward(view, weights, seen2)
    assert bonus == 0.0 and (seen3 == seen2).all()
    # Batched: three episodes at once equal three single calls.
    views = np.array([[True, True, False, False], [False, False, False, True], [False, False, True, True]])
    seens = np.array([[False, True, False, False], [False] * 4, [False] * 4])
    bonus_b, seen_b = parent_reward(views, np.tile(weights, (3, 1)), seens)
    for b in range(3):
        one, s = parent_reward(views[b], weights, seens[b])
        assert bonus_b[b] == pytest.approx(one) and (seen_b[b] == s).all()
    assert bonus_b.tolist() == pytest.approx([0.0, 0.0, 0.3])


def test_parent_reward_by_name_and_weights_agree():
    parents = parents_of("kitchen", "Toaster")
    w = parent_weights("kitchen", "Toaster")
    names = category_set().names
    assert {names[i] for i in np.flatnonzero(w)} == set(parents)
    bonus, seen = parent_reward_by_name({"CounterTop", "StoveBurner", "Apple"}, parents, set())
    assert bonus == pytest.approx(parents["CounterTop"]) and seen == {"CounterTop"}
    bonus, seen = parent_reward_by_name({"CounterTop", "StoveBurner"}, parents, seen)
    assert bonus == pytest.approx(parents["StoveBurner"]) and seen == {"CounterTop", "StoveBurner"}
    assert parent_reward_by_name({"Apple"}, parents, set()) == (0.0, set())


def outside_references(data: bytes, depth: int) -> list[str]:
    """What in a file's contents points outside the repository: the shared data folder, a quoted
    absolute or parent-relative path, or ``__file__`` climbed more than ``depth`` folders (the
    file's depth below the repository root). Binary files are checked for the folder names only."""
    found = [spelling for spelling in SHARED_SPELLINGS if spelling.encode() in data]
    try:
        text = data.decode()
    except UnicodeDecodeError:
        return found
    found += [match.group(0) for match in OUTSIDE_PATH_LITERAL.finditer(text)]
    for match in FILE_CLIMB.finditer(text):
        before, index, after = match.groups()
        ups = before.count(".parent") + (int(index) + 1 if index else 0) + after.count(".parent")
        if ups > depth:
            found.append(match.group(0))
    return found


def test_the_outside_reference_check_finds_what_it_should():
    file = "__file__" + ")"  # spelled apart, so that this file passes its own check
    shared = SHARED_SPELLINGS[0]
    name = "'shared'"
    assert outside_references(f"ROOT = Path({file}.resolve().parents[1].parent / {name}".encode(), 2)
    assert outside_references(f"ROOT = Path({file}.parent.parent.parent".encode(), 2)
    assert outside_references(f"SAMPLE = '{shared}/data/x.pkl'".encode(), 2)
    assert outside_references(b'Path("' + b"/" + b'tmp/x").touch()', 2)
    assert outside_references(b"\x80\x03" + shared.encode() + b"\xf0", 2)
    assert not outside_references(f"Path({file}.resolve().parents[1] / 'mapless'".encode(), 2)
    assert not outside_references(f"Path({file}.parent.parent.glob('experiments/*.yaml')".encode(), 2)
    assert not outside_references(b"shared memory, shared_gcn_term, tmp_path / 'x.pkl'", 2)


def test_package_and_tests_never_read_the_shared_folder_and_data_has_provenance():
    for folder in ("knowledge", "models"):
        for path in (PACKAGE / folder).glob("*.py"):
            assert not any(spelling in path.read_text() for spelling in SHARED_SPELLINGS), path
    checked = 0
    for path in sorted(TESTS.rglob("*")):
        if path.is_file() and "__pycache__" not in path.parts:
            found = outside_references(path.read_bytes(), depth=len(path.relative_to(REPO).parts))
            assert not found, (path, found)
            checked += 1
    assert checked > 30 and (TESTS / "data" / "hoz_bathroom_val_22_sample.pkl").is_file()
    for notice, folder in (
        (PACKAGE / "data" / "priors" / "NOTICE.md", PACKAGE / "data" / "priors"),
        (TESTS / "data" / "README.md", TESTS / "data"),
    ):
        text = notice.read_text()
        for path in folder.iterdir():
            if path != notice:
                assert path.name in text, path.name
