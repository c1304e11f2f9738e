"""SAVN/MJOLNIR offline data both ways.

Scene folders: ``format`` (the file layout), ``reader``, ``writer``. Evaluation episode pickles:
``episodes`` (read and map onto the built-in scenes), ``episode_writer``; :mod:`mapless.safe_pickle`
reads a published pickle without running its code.
"""

from mapless.offline.episode_writer import write_episode_file
from mapless.offline.episodes import (
    MappingReport,
    RawEpisode,
    import_episode_file,
    map_episodes,
    read_episode_file,
)
from mapless.offline.format import FORMATS, OfflineFormatError, scene_folder_name
from mapless.offline.reader import find_scene_folder, load_offline_scene, offline_library, offline_loader
from mapless.offline.writer import export_scene

__all__ = [
    "FORMATS",
    "MappingReport",
    "OfflineFormatError",
    "RawEpisode",
    "export_scene",
    "find_scene_folder",
    "import_episode_file",
    "load_offline_scene",
    "map_episodes",
    "offline_library",
    "offline_loader",
    "read_episode_file",
    "scene_folder_name",
    "write_episode_file",
]
