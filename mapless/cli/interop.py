"""``mapless export``, ``mapless thor scrape`` and ``mapless interop ...``: AI2-THOR interop.

* ``mapless export SCENES --format savn|mjolnir --out DIR``: built-in scenes as SAVN/MJOLNIR
  offline folders.
* ``mapless thor scrape SCENES --out DIR``: offline folders scraped from a live AI2-THOR.
* ``mapless interop check DIR``: load offline folders as training would and summarise them.
* ``mapless interop episodes-import FILE.pkl...``: map published episode pickles onto the built-in
  scenes, or onto an offline root's (a mapless episode file), with a mapping report per file and
  cause; ``hoz22`` names the shipped published files (the reference protocol's sets).
* ``mapless interop episodes-export SOURCE --format savn|mjolnir --out DIR``: our episode sets as
  evaluation pickles for the original code bases, one per room type.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from mapless.cli.common import (
    SCENES_HELP,
    DeprecatedAlias,
    add_category_set_argument,
    add_command,
    add_sim_arguments,
    sim_config_from,
)
from mapless.errors import MaplessError
from mapless.offline import offline_library
from mapless.offline.format import FORMATS

FORMAT_HELP = (
    "offline folder layout: savn, or mjolnir (features without the batch axis, plus objects_bb.json)"
)


def register(subparsers: argparse._SubParsersAction) -> None:
    export = add_command(
        subparsers, "export", _export, sim=True, help="write built-in scenes as SAVN/MJOLNIR offline folders"
    )
    export.add_argument("scenes", help=SCENES_HELP)
    export.add_argument("--format", choices=FORMATS, default="savn", help=FORMAT_HELP)
    export.add_argument("--out", type=Path, required=True, help="offline data root (one folder per scene)")
    export.add_argument("--no-compression", action="store_true", help="write the feature HDF5 uncompressed")

    thor = subparsers.add_parser("thor", help="live AI2-THOR backend (needs the mapless[thor] extra)")
    thor_sub = thor.add_subparsers(dest="thor_command", required=True)
    scrape = add_command(
        thor_sub, "scrape", _scrape, help="breadth-first search over poses into offline folders"
    )
    scrape.add_argument("scenes", help=SCENES_HELP)
    scrape.add_argument("--out", type=Path, required=True, help="offline data root (one folder per scene)")
    scrape.add_argument("--format", choices=FORMATS, default="savn", help=FORMAT_HELP)
    add_sim_arguments(scrape, cache=False)
    # Old spellings of --sim visibility_distance=M, --sim horizons=[0,30] and --sim horizontal_fov=90.
    scrape.add_argument(
        "--visibility-distance", action=DeprecatedAlias, replacement="--sim", sim_key="visibility_distance"
    )
    scrape.add_argument(
        "--horizons",
        action=DeprecatedAlias,
        replacement="--sim",
        sim_key="horizons",
        to_yaml=lambda text: f"[{text}]",
    )
    scrape.add_argument(
        "--field-of-view", action=DeprecatedAlias, replacement="--sim", sim_key="horizontal_fov"
    )
    add_category_set_argument(scrape)
    scrape.add_argument(
        "--platform",
        help="ai2thor platform, e.g. CloudRendering for headless Vulkan (default: ai2thor's choice)",
    )
    scrape.add_argument("--commit-id", help="pin the AI2-THOR build (default: ai2thor's own)")
    scrape.add_argument(
        "--local-executable-path",
        help="use an already downloaded AI2-THOR build (default: ai2thor downloads its build)",
    )
    scrape.add_argument("--images", action="store_true", help="also write images.hdf5 with the RGB frames")

    interop = subparsers.add_parser("interop", help="check offline folders, import/export episode pickles")
    sub = interop.add_subparsers(dest="interop_command", required=True)
    check = add_command(sub, "check", _check, help="load offline scene folders and summarise them")
    check.add_argument("folders", nargs="+", type=Path, help="scene folders, or roots holding them")
    add_category_set_argument(check)
    check.add_argument(
        "--visible-file",
        default="visible_object_map.json",
        help="name of the visible-object map in each scene folder",
    )
    check.add_argument("--no-features", action="store_true", help="skip reading the feature HDF5")

    imp = add_command(
        sub,
        "episodes-import",
        _import_episodes,
        sim=True,
        help="map SAVN/MJOLNIR/HOZ episode pickles onto the built-in (or an offline root's) scenes",
        description="Prints each file's mapping report and, for several files, a table of them (episodes "
        "mapped, how targets and starts matched, skipped episodes per cause). FILE 'hoz22' stands for "
        "the shipped published files, the reference protocol's sets: map them under its rule with "
        "--sim visibility_distance=1.5.",
    )
    imp.add_argument("files", nargs="+", metavar="FILE", help="episode pickles (.pkl, .pkl.gz), or hoz22")
    imp.add_argument(
        "--out",
        type=Path,
        help="mapless episode file to write (.json.gz), every file's episodes (default: report only)",
    )
    imp.add_argument("--max-target-distance", type=float, default=0.5, help="m, horizontal (default 0.5)")
    imp.add_argument("--max-start-distance", type=float, default=0.36, help="m (default 0.36)")
    imp.add_argument("--target-set", default="imported", help="label stored in the episode file")
    imp.add_argument("--show-skipped", action="store_true", help="list every skipped episode")
    imp.add_argument(
        "--offline-dir",
        type=Path,
        help="map onto the scenes of this SAVN/MJOLNIR offline root instead of the built-in ones "
        "(for evaluation with `mapless eval --offline-dir`: object ids then match the root's; "
        "default: the built-in scenes)",
    )

    exp = add_command(
        sub,
        "episodes-export",
        _export_episodes,
        sim=True,
        help="write a mapless episode set as SAVN/MJOLNIR pickles, one per room type",
        description="Writes OUT/<room>_<test|val|test_val>.pkl, the layout the references read (or one "
        "OUT.pkl with every room). task_data lists only the target ids of the scenes' visible-object "
        "maps, as `mapless export` writes them under the same simulator settings.",
    )
    exp.add_argument(
        "source",
        help="a built-in split (val, test, paper, ref_val, ref_test) or a mapless episode file",
    )
    exp.add_argument("--format", choices=FORMATS, default="savn", help=FORMAT_HELP)
    exp.add_argument(
        "--out",
        type=Path,
        required=True,
        help="folder for the per-room files (FILE.pkl: one file with every room type)",
    )
    exp.add_argument(
        "--target-set",
        default="mjolnir22",
        help="target set of a built-in split (default mjolnir22, shipped; others, e.g. savn, are made "
        "on demand as `mapless episodes make --target-set NAME` makes them)",
    )
    exp.add_argument(
        "--glove-set",
        default="mjolnir101",
        help="packaged GloVe table: mjolnir101 (MJOLNIR's v1 table) or all_types",
    )
    exp.add_argument(
        "--glove",
        type=Path,
        help="HDF5 with one GloVe vector per type, e.g. SAVN's glove_map300d.hdf5 (default: --glove-set)",
    )


def _export(args: argparse.Namespace) -> int:
    from mapless.offline.writer import export_scene
    from mapless.scenes.catalogue import resolve_scenes
    from mapless.sim.cache import load_or_build

    config = sim_config_from(args)
    args.out.mkdir(parents=True, exist_ok=True)
    for name in resolve_scenes(args.scenes):
        start = time.perf_counter()
        data = load_or_build(name, config, args.cache_dir)
        folder = export_scene(
            data, args.out, args.format, compression=None if args.no_compression else "gzip"
        )
        print(
            f"{folder}: {data.n_poses} poses, {len(set(data.visible_matrix_csr[1].tolist()))} visible "
            f"instances, {time.perf_counter() - start:.1f} s"
        )
    return 0


def _scrape(args: argparse.Namespace) -> int:
    from mapless.config import load_config
    from mapless.scenes.catalogue import resolve_scenes
    from mapless.sim.config import SimConfig
    from mapless.thor import ThorConfig, make_controller, scrape

    extra = {
        k: v
        for k, v in (("commit_id", args.commit_id), ("local_executable_path", args.local_executable_path))
        if v
    }
    # --sim names every setting; --category-set stands for --sim category_set=..., which wins if given.
    sim = load_config(SimConfig, args.sim_config, [f"category_set={args.category_set}", *args.sim])
    config = ThorConfig(sim, platform=args.platform, extra=extra)
    scenes = resolve_scenes(args.scenes)
    controller = make_controller(scenes[0], config)
    try:
        for name in scenes:
            start = time.perf_counter()
            folder = scrape(
                controller, name, args.out, args.format, config, images=args.images, progress=True
            )
            print(f"{folder}: scraped in {time.perf_counter() - start:.0f} s")
    finally:
        controller.stop()
    return 0


def _scene_folders(paths: list[Path]) -> list[Path]:
    folders = []
    for path in paths:
        if (path / "graph.json").exists() or not path.is_dir():
            folders.append(path)
        else:
            found = sorted(p.parent for p in path.glob("*/graph.json"))
            if not found:
                raise MaplessError(
                    f"{path}: neither a scene folder nor a folder of scene folders (no graph.json)"
                )
            folders.extend(found)
    return folders


def _check(args: argparse.Namespace) -> int:
    import numpy as np

    from mapless.offline.reader import load_offline_scene

    for folder in _scene_folders(args.folders):
        sd = load_offline_scene(
            folder, args.category_set, "none" if args.no_features else "auto", visible_file=args.visible_file
        )
        moves = int((sd.successors != np.arange(sd.n_poses)[:, None]).sum())
        targets = len(set(sd.visible_matrix_csr[1].tolist()))
        print(
            f"{folder}: {sd.scene} ({sd.room_type}), {sd.n_poses} poses, {moves} successful moves, "
            f"{targets} visible instances, features {tuple(sd.features.shape[1:])} {sd.meta['feature_kind']}, "
            f"boxes {'yes' if sd.meta['has_boxes'] else 'no'}"
        )
    return 0


def _import_episodes(args: argparse.Namespace) -> int:
    from mapless.episodes import evalsets
    from mapless.offline.episodes import import_episode_file, mapping_table
    from mapless.scenes.catalogue import SPLITS
    from mapless.sim.cache import fingerprint
    from mapless.sim.library import SceneLibrary

    config = sim_config_from(args)
    if args.offline_dir:
        library = offline_library(args.offline_dir, config.category_set)
    else:
        library = SceneLibrary.builtin(config, args.cache_dir)
    files = [f for name in args.files for f in _episode_files(name)]
    reports = {}
    for file in files:
        # One file keeps the plain prefix; several are told apart by their name (kitchen_val_22/...).
        prefix = "import" if len(files) == 1 else file.name.split(".")[0]
        report = import_episode_file(
            file,
            scene_data=library.__getitem__,
            max_target_distance=args.max_target_distance,
            max_start_distance=args.max_start_distance,
            id_prefix=prefix,
        )
        reports[file.name] = report
        print(f"{file}: {report.summary()}")
        if args.show_skipped:
            for index, reason in report.skipped:
                print(f"  #{index}: {reason}")
    if len(reports) > 1:
        print(mapping_table(reports))
    if args.out is not None:
        episodes = [e for report in reports.values() for e in report.episodes]
        if not episodes:
            raise MaplessError(f"{', '.join(args.files)}: no episode could be mapped; nothing written")
        numbers = {int(e.scene.removeprefix("FloorPlan")) % 100 for e in episodes}
        # The file header names the scene range; pick the narrowest split holding every scene.
        split = next(
            s for s in ("val", "test", "ref_val", "ref_test", "paper", "all") if numbers <= set(SPLITS[s])
        )
        evalsets.save(args.out, episodes, split, args.target_set, 0, fingerprint(config))
        print(f"wrote {args.out}: {len(episodes)} episodes (split label {split})")
    return 0


def _episode_files(name: str) -> list[Path]:
    """An episode file, or every shipped file of a published set (``hoz22``), room by room."""
    from mapless.episodes.evalsets import PUBLISHED, published_path
    from mapless.scenes.catalogue import ROOM_TYPES

    if name not in PUBLISHED or Path(name).exists():
        return [Path(name)]
    return [published_path(name, split, room) for room in ROOM_TYPES for split in PUBLISHED[name][1]]


def _glove_from_hdf5(path: Path) -> dict:
    import h5py
    import numpy as np

    from mapless.offline.format import OfflineFormatError

    try:
        with h5py.File(path, "r") as f:
            return {name: np.asarray(f[name][()], dtype=np.float32) for name in f}
    except OSError as error:
        raise OfflineFormatError(path, f"not a readable HDF5 file ({error})") from None


def _export_episodes(args: argparse.Namespace) -> int:
    import numpy as np

    from mapless.episodes import evalsets
    from mapless.episodes.protocols import PROTOCOLS, protocol_of_split
    from mapless.offline.episode_writer import (
        REFERENCE_EPISODES_PER_ROOM,
        write_episode_file,
        write_room_files,
    )
    from mapless.scenes.catalogue import room_type_of
    from mapless.sim.cache import fingerprint
    from mapless.sim.library import SceneLibrary

    base = sim_config_from(args)
    path = Path(args.source)
    if path.exists():
        episodes, header = evalsets.load(path)
        split = header["split"]
        # The visible-object maps follow the success rule the file was made under, if it is a protocol's.
        rules = [base, *(p.sim(base) for p in PROTOCOLS.values())]
        config = next((c for c in rules if fingerprint(c) == header["sim_fingerprint"]), base)
    else:
        split = args.source
        path = evalsets.source_path(split, args.target_set)
        episodes = evalsets.load(path)[0] if path.exists() else None
        config = protocol_of_split(split).sim(base)
    library = SceneLibrary.builtin(config, args.cache_dir)
    if episodes is None:
        print(
            f"no built-in {split} set of target set {args.target_set}: making it (seed 0, 250 per room type)"
        )
        episodes = evalsets.make_eval_set(library, split, args.target_set)
    if args.glove is not None:
        embeddings = _glove_from_hdf5(args.glove)
    else:
        from mapless.knowledge.glove import glove_table

        embeddings = glove_table(args.glove_set)

    def visible_ids(scene: str) -> set[str]:
        data = library[scene]
        return {data.instance_ids[i] for i in np.unique(data.visible_matrix_csr[1])}

    kwargs = {"embeddings": embeddings, "visible_ids": visible_ids}
    if args.out.suffix == ".pkl":
        count = write_episode_file(episodes, args.out, args.format, **kwargs)
        print(f"wrote {args.out}: {count} episodes in the {args.format} pickle format")
        return 0
    files = write_room_files(episodes, args.out, split, args.format, **kwargs)
    for room, file in files.items():
        count = sum(room_type_of(e.scene) == room for e in episodes)
        short = count < REFERENCE_EPISODES_PER_ROOM
        note = f" (fewer than the references' --num_ep {REFERENCE_EPISODES_PER_ROOM})" if short else ""
        print(f"wrote {file}: {count} episodes in the {args.format} pickle format{note}")
    return 0
