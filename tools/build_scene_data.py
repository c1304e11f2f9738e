"""Convert the shared iTHOR layouts into the package's compact scene file.

Developer tool, run once when the upstream data changes; the package itself never
reads ``../shared``.  Output: ``mapless/data/scenes/ithor_v5_scenes.json.gz``.

    python tools/build_scene_data.py ../shared/data/ithor
"""

from __future__ import annotations

import gzip
import json
import sys
from pathlib import Path


def _round(values, ndigits: int = 3):
    return [round(float(v), ndigits) for v in values]


def convert(shared: Path) -> dict:
    compact = json.loads(gzip.decompress((shared / "derived" / "ithor_scenes_compact.json.gz").read_bytes()))
    reachable = json.loads((shared / "derived" / "ithor_reachable_positions.json").read_text())
    scenes = {}
    for name, scene in compact.items():
        full = json.loads((shared / "layouts" / "metadata_v5" / f"{name}_physics.json").read_text())
        objects = []
        for obj in scene["objects"]:
            meta = full[obj["objectId"]]
            objects.append(
                {
                    "id": obj["objectId"],
                    "type": obj["objectType"],
                    "name": obj["name"],
                    "center": _round(obj["aabb_center"]),
                    "size": _round(obj["aabb_size"]),
                    "footprint": obj["oobb_footprint_xz"],
                    "parents": obj["parentReceptacles"] or [],
                    "receptacle": obj["receptacle"],
                    "pickupable": obj["pickupable"],
                    "moveable": obj["moveable"],
                    "openable": obj["openable"],
                    "is_open": bool(meta["isOpen"]),
                }
            )
        scenes[name] = {
            "room_type": scene["room_type"],
            "floor_center": scene["floor_aabb"]["center"],
            "floor_size": scene["floor_aabb"]["size"],
            "reachable": sorted(map(tuple, reachable[name]["union_minus_obstacle_hits"])),
            "objects": objects,
        }
    return {
        "format": "mapless-ithor-scenes/1",
        "source": "AI2-THOR >=5.0.0 default layouts (Kajiih/rl_ai2thor @ 5907c98, MIT) and the "
        "union_minus_obstacle_hits reachable grid (ALFRED, AllenAct, rearrangement-2023). "
        "See mapless/data/NOTICE.md.",
        "scenes": scenes,
    }


def main() -> None:
    shared = Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/ithor")
    out = Path(__file__).resolve().parents[1] / "mapless" / "data" / "scenes" / "ithor_v5_scenes.json.gz"
    data = convert(shared)
    # mtime=0: the same input gives the same bytes (the file's hash selects the scene cache).
    out.write_bytes(gzip.compress(json.dumps(data, separators=(",", ":")).encode(), compresslevel=9, mtime=0))
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB, {len(data['scenes'])} scenes)")


if __name__ == "__main__":
    main()
