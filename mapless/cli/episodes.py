"""``mapless episodes make | show``."""

from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np

from mapless.cli.common import (
    TARGET_SET_HELP,
    DeprecatedAlias,
    add_command,
    positive_int,
    seed_int,
    sim_config_from,
)
from mapless.episodes import evalsets
from mapless.errors import MaplessError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("episodes", help="make and inspect fixed evaluation episode sets")
    sub = parser.add_subparsers(dest="episodes_command", required=True)

    make = add_command(
        sub,
        "make",
        _make,
        sim=True,
        help="(re)generate evaluation episode files deterministically from a seed",
    )
    make.add_argument(
        "--split",
        dest="splits",
        default=",".join(evalsets.EVAL_SPLITS),
        help="one split or several, comma-separated: val, test, paper (the standard and paper protocols, success within 1.0 m) and ref_val, "
        "ref_test (the reference protocol, 1.5 m); each is made under its protocol's success rule",
    )
    make.add_argument(
        "--target-set",
        default="mjolnir22",
        help="the training target set whose sets to make (mapless.scenes.categories.TARGET_SETS): mjolnir22, "
        "savn (sampled), or hoz22, whose ref_val and ref_test sets are the shipped published HOZ files "
        "mapped onto the scenes (--per-room and --seed do not apply; with their mapping report) and "
        "whose other splits are sampled over its classes",
    )
    make.add_argument("--splits", action=DeprecatedAlias, replacement="--split")
    make.add_argument("--per-room", type=positive_int, default=250, help="episodes per room type")
    make.add_argument("--seed", type=seed_int, default=0, help="sampling seed (>= 0)")
    make.add_argument(
        "--out",
        type=Path,
        default=Path("episodes"),
        help="folder of the episode files (SPLIT_TARGETSET.json.gz)",
    )
    make.add_argument(
        "--check", action="store_true", help="also compare with the built-in files byte for byte"
    )
    make.add_argument(
        "--layouts",
        help="SOURCE:PER_SCENE: a layout-shift set, each episode on one of its floor plan's first PER_SCENE "
        "variants from SOURCE (gen: generated arrangements; rearrange2023; or an arrangement file in the "
        "rearrangement dataset's format), e.g. --split test --layouts gen:3 (default: the default layouts) (docs/guide/simulator.md)",
    )

    show = add_command(
        sub, "show", _show, sim=True, help="summary of an episode set, or a picture of one episode"
    )
    show.add_argument("source", help="a split name (built-in set) or an episode file")
    show.add_argument("--target-set", default="mjolnir22", help=f"{TARGET_SET_HELP} (of a built-in split)")
    show.add_argument("--index", type=int, help="draw this episode (needs --out; default: draw none)")
    show.add_argument(
        "--out", type=Path, help="PNG file of the episode drawn with --index (required with it)"
    )


def _make(args: argparse.Namespace) -> int:
    from mapless.episodes.protocols import protocol_of_split
    from mapless.sim.cache import fingerprint
    from mapless.sim.config import SimConfig
    from mapless.sim.library import SceneLibrary

    base = sim_config_from(args)
    mismatches = 0
    libraries: dict[SimConfig, SceneLibrary] = {}
    splits = args.splits.split(",")
    unknown = [split for split in splits if split not in evalsets.EVAL_SPLITS]
    if unknown:  # before any set is made: one bad name among several writes none
        raise MaplessError(f"no evaluation split {unknown[0]!r}; choose from {evalsets.EVAL_SPLITS}")
    for split in splits:
        config = protocol_of_split(split).sim(base)
        library = libraries.setdefault(config, SceneLibrary.builtin(config, args.cache_dir))
        if evalsets.is_published(split, args.target_set) and not args.layouts:
            from mapless.offline.episodes import mapping_table

            episodes, reports = evalsets.map_published(library, split, args.target_set)
            print(mapping_table(reports))
        else:
            episodes = evalsets.make_eval_set(
                library, split, args.target_set, args.per_room, args.seed, layouts=args.layouts
            )
        label = f"{split}_{evalsets.layouts_label(args.layouts)}" if args.layouts else split
        path = args.out / f"{label}_{args.target_set}.json.gz"
        evalsets.save(path, episodes, split, args.target_set, args.seed, fingerprint(config), args.layouts)
        print(f"wrote {path}: {len(episodes)} episodes")
        if args.check:
            builtin = evalsets.builtin_path(split, args.target_set, args.layouts)
            same = builtin.is_file() and path.read_bytes() == builtin.read_bytes()
            print(f"  identical to the built-in {split} set: {same}")
            mismatches += not same
    return 1 if mismatches else 0


def _show(args: argparse.Namespace) -> int:
    episodes, header = evalsets.load(evalsets.source_path(args.source, args.target_set))
    print(
        f"{len(episodes)} episodes, split {header['split']} ({header['scenes']}), seed {header.get('seed')}"
    )
    by_room = collections.defaultdict(list)
    for e in episodes:
        by_room[e.episode_id.split("/")[1] if "/" in e.episode_id else "?"].append(e)
    for room, eps in by_room.items():
        lengths = np.array([e.optimal_length for e in eps])
        counts = collections.Counter(e.target for e in eps)
        print(
            f"  {room:<12} {len(eps):>4} eps  L mean {lengths.mean():.1f}  L>=5 {np.mean(lengths >= 5):.0%}  "
            + ", ".join(f"{t} {n}" for t, n in counts.most_common())
        )
    if args.index is not None:
        if args.out is None:
            raise MaplessError("--index needs --out PNG")
        if not 0 <= args.index < len(episodes):
            raise MaplessError(f"--index {args.index}: the set has episodes 0 to {len(episodes) - 1}")
        _draw(episodes[args.index], args)
    return 0


def _draw(episode, args: argparse.Namespace) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mapless.scenes.layout import load_scene
    from mapless.sim.pictures import draw_top_down, egocentric_view

    config = sim_config_from(args)
    scene = load_scene(episode.scene)
    fig, (top, ego) = plt.subplots(1, 2, figsize=(13, 6))
    draw_top_down(top, scene, config, (episode.target,), episode.start)
    ego.imshow(egocentric_view(scene, config, *episode.start, size=210))
    ego.set_title(f"{episode.episode_id}: find {episode.target} (L*={episode.optimal_length})")
    ego.axis("off")
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")
