"""SAVN/MJOLNIR offline data both ways: scene folders (reader, writer) and episode pickles."""

from mapless.offline.episodes import (
    MappingReport,
    RawEpisode,
    import_episode_file,
    map_episodes,
    read_episode_file,
    write_episode_file,
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
