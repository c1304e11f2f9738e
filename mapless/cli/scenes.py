"""``mapless scenes build | list | show | check | targets``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from mapless.cli.common import (
    SCENES_HELP,
    TARGET_SET_HELP,
    add_command,
    parse_pose,
    positive_int,
    sim_config_from,
)
from mapless.errors import MaplessError, UnknownNameError
from mapless.files import unwritable
from mapless.scenes.catalogue import ROOM_TYPES, resolve_scenes, scene_names, split_of
from mapless.scenes.categories import targets
from mapless.scenes.layout import load_scene
from mapless.sim.scene_data import USABLE_COMPONENT_SHARE


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("scenes", help="build, list, inspect and check the built-in scenes")
    sub = parser.add_subparsers(dest="scenes_command", required=True)

    build = add_command(
        sub, "build", _build, sim=True, help="precompute and cache scenes (all 120 by default)"
    )
    build.add_argument("scenes", nargs="?", default="all", help=SCENES_HELP)
    build.add_argument("--workers", type=positive_int, default=2, help="scenes built in parallel processes")
    build.add_argument("--rebuild", action="store_true", help="ignore existing cache entries")

    listing = add_command(sub, "list", _list, help="scenes with room type, split, object and grid counts")
    listing.add_argument("scenes", nargs="?", default="all", help=SCENES_HELP)

    show = add_command(
        sub, "show", _show, sim=True, help="top-down map and egocentric view of a scene as a PNG"
    )
    show.add_argument("scene", help="a FloorPlan name, e.g. FloorPlan1")
    show.add_argument(
        "--pose",
        type=parse_pose,
        help="x,z,yaw,horizon; write --pose=-1.25,0.5,90,0 when x is negative (default: first reachable pose)",
    )
    show.add_argument("--target", action="append", default=[], help="object type to highlight (repeatable)")
    show.add_argument("--out", type=Path, required=True, help="PNG file to write")

    check = add_command(
        sub,
        "check",
        _check,
        sim=True,
        help="per scene: poses, pose-graph components, reachable targets, share of poses seeing an "
        "object; then every target instance no pose can see, under each protocol's success rule",
    )
    check.add_argument("scenes", nargs="?", default="all", help=SCENES_HELP)
    check.add_argument("--target-set", default="mjolnir22", help=TARGET_SET_HELP)
    check.add_argument(
        "--protocols",
        default="standard,reference",
        help="protocols whose success rule the never-visible targets are listed under (the table uses the "
        "first); each rule has its own scene cache, built on first use",
    )

    variants = add_command(
        sub,
        "variants",
        _variants,
        help='facts about an arrangement source against the default layouts (docs/guide/simulator.md, "Scene variants")',
    )
    variants.add_argument(
        "source", nargs="?", default="rearrange2023", help="rearrange2023 or an arrangement file"
    )
    variants.add_argument(
        "--phase",
        choices=("target", "start"),
        default="target",
        help="which arrangement of each rearrangement episode: its goal (target) or its shuffled one (start)",
    )

    target_parser = add_command(
        sub, "targets", _targets, help="how many scenes of each split contain each target"
    )
    target_parser.add_argument("--target-set", default="mjolnir22", help=TARGET_SET_HELP)


def _build(args: argparse.Namespace) -> int:
    from mapless.sim.cache import build_many, cache_path

    config = sim_config_from(args)
    scenes = resolve_scenes(args.scenes)
    start = time.perf_counter()
    build_many(scenes, config, args.cache_dir, workers=args.workers, rebuild=args.rebuild)
    folder = cache_path(scenes[0], config, args.cache_dir).parent
    print(f"{len(scenes)} scenes ready in {time.perf_counter() - start:.0f} s; cache: {folder}")
    return 0


def _list(args: argparse.Namespace) -> int:
    print(f"{'scene':<14}{'room':<13}{'split':<7}{'objects':>8}{'grid':>6}")
    for name in resolve_scenes(args.scenes):
        scene = load_scene(name)
        print(
            f"{name:<14}{scene.room_type:<13}{scene.split:<7}{len(scene.objects):>8}{len(scene.reachable):>6}"
        )
    return 0


def _show(args: argparse.Namespace) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mapless.sim.library import SceneLibrary
    from mapless.sim.pictures import draw_top_down, egocentric_view

    problem = unwritable(args.out.parent, [args.out.name])
    if problem is not None:  # before the scene is built and drawn
        raise MaplessError(f"--out {args.out}: {problem}")
    config = sim_config_from(args)
    scene = load_scene(args.scene)
    present = sorted({o.type for o in scene.objects})
    for target in args.target:
        if target not in present:
            raise UnknownNameError(f"object type in {scene.name}", target, present)
    if args.pose is None:
        x, z = scene.reachable[0]
        pose = (float(x), float(z), 0, config.horizons[0])
    else:
        pose = args.pose
        SceneLibrary.builtin(config, args.cache_dir).pose_of(scene.name, pose)  # validates, names nearest
    fig, (top, ego) = plt.subplots(1, 2, figsize=(13, 6))
    draw_top_down(top, scene, config, tuple(args.target), pose)
    ego.imshow(egocentric_view(scene, config, *pose, size=210))
    ego.set_title(f"egocentric view at {pose}")
    ego.axis("off")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")
    return 0


def _check(args: argparse.Namespace) -> int:
    from mapless.episodes.protocols import get_protocol
    from mapless.sim.library import SceneLibrary

    base = sim_config_from(args)
    protocols = [get_protocol(name) for name in args.protocols.split(",")]
    libraries = {p.name: SceneLibrary.builtin(p.sim(base), args.cache_dir) for p in protocols}
    room_targets = targets(args.target_set)
    scenes = resolve_scenes(args.scenes)
    first = protocols[0]
    config = first.sim(base)
    print(f"Under the {first.name} protocol (success within {first.visibility_distance} m):")
    print(
        f"{'scene':<14}{'poses':>7}{'positions':>10}{'components':>12}  {'targets reachable':<20}"
        f"{'sees object':>12}{'sees target':>12}{'geo/eucl':>10}"
    )
    for name in scenes:
        data = libraries[first.name][name]
        wanted = [t for t in room_targets[data.room_type] if len(data.instances_of(t))]
        usable_starts = (data.horizon == 0) & data.usable_poses
        reachable = [t for t in wanted if (data.target_distances(t)[usable_starts] >= 0).any()]
        sees_object = np.diff(data.view_ptr) > 0
        goal_any = np.zeros(data.n_poses, bool)
        for t in wanted:
            goal_any |= data.goal_mask(t)
        print(
            f"{name:<14}{data.n_poses:>7}{data.n_poses // (len(config.yaws) * len(config.horizons)):>10}"
            f"{_components(data):>12}  "
            f"{len(reachable)}/{len(wanted)} ({len(room_targets[data.room_type])} in set){'':<4}"
            f"{sees_object.mean():>11.0%}{goal_any.mean():>12.0%}{_detour_ratio(data):>10.2f}"
        )
    print("components: poses per strongly connected component of the pose graph; episodes start only in the")
    print(f"usable ones (those holding at least {USABLE_COMPONENT_SHARE:.0%} of the largest one's poses)")
    for protocol in protocols:
        never = [
            (name, ids)
            for name in scenes
            if (ids := _never_visible(libraries[protocol.name][name], room_targets))
        ]
        print(
            f"\nTarget instances no pose can see under the {protocol.name} protocol "
            f"(success within {protocol.visibility_distance} m): {sum(len(ids) for _, ids in never)}"
        )
        for name, ids in never:
            print(f"  {name}: {', '.join(ids)}")
    return 0


def _components(data) -> str:
    """``1``, or the pose count of each component (largest first) joined by ``+``."""
    sizes = np.bincount(data.components)
    return "1" if len(sizes) == 1 else "+".join(str(n) for n in sizes)


def _never_visible(data, room_targets: dict) -> list[str]:
    """Ids of the scene's instances of its room's target types that no pose sees (in view, within
    the success rule's distance, not inside a closed receptacle)."""
    seen = set(np.unique(data.visible_matrix_csr[1]).tolist())
    wanted = set(room_targets[data.room_type])
    return [
        iid
        for i, (iid, kind) in enumerate(zip(data.instance_ids, data.instance_types, strict=True))
        if kind in wanted and i not in seen
    ]


def _detour_ratio(data) -> float:
    """Median ratio of grid geodesic to straight-line distance between connected positions."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import shortest_path

    xz = np.round(np.stack([data.x, data.z], 1), 2)
    positions, position_of = np.unique(xz, axis=0, return_inverse=True)
    moves = data.successors[:, 0]
    src, dst = position_of[np.arange(data.n_poses)], position_of[moves]
    edges = np.unique(np.stack([src, dst], 1)[src != dst], axis=0)  # one edge per position pair
    lengths = np.linalg.norm(positions[edges[:, 0]] - positions[edges[:, 1]], axis=1)
    graph = coo_matrix((lengths, (edges[:, 0], edges[:, 1])), shape=(len(positions),) * 2).tocsr()
    geodesic = shortest_path(graph, directed=True)
    euclid = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    ok = np.isfinite(geodesic) & (euclid > 0)
    return float(np.median(geodesic[ok] / euclid[ok])) if ok.any() else float("nan")


def _variants(args: argparse.Namespace) -> int:
    from mapless.scenes.variants import source_facts

    f = source_facts(args.source, args.phase)
    print(
        f"{args.source} ({args.phase} arrangements): {f['arrangements']} arrangements of {f['floor_plans']} floor plans"
    )
    print(
        f"  apply without error: {f['applicable']} ({f['applicable'] / max(f['arrangements'], 1):.1%}); the rest place an object off every surface"
    )
    print(
        f"  listed objects more than 0.5 m from their default pivot: {f['moved_05']} of {f['listed']} ({f['moved_share']:.1%})"
    )
    print(
        f"  pickupable objects an arrangement leaves out (removed): {f['removed']} of {f['slots']} ({f['removed_share']:.1%})"
    )
    print(
        f"  pickupable types of a floor plan that none of its arrangements lists: {f['absent_type_share']:.1%}"
    )
    return 0


def _targets(args: argparse.Namespace) -> int:
    room_targets = targets(args.target_set)
    splits = ("train", "val", "test")
    print(f"{'room':<13}{'target':<16}" + "".join(f"{s:>7}" for s in splits))
    for room in ROOM_TYPES:
        for target in room_targets[room]:
            counts = {s: 0 for s in splits}
            for name in scene_names("all", (room,)):
                if load_scene(name).instances_of(target):
                    counts[split_of(name)] += 1
            print(
                f"{room:<13}{target:<16}"
                + "".join(f"{counts[s]:>4}/{len(scene_names(s, (room,)))}" for s in splits)
            )
    return 0
