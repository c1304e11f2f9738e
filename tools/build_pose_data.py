"""Extract the default pivot pose of every movable object of the 120 floor plans.

Arrangements in the rearrangement dataset's format give an object's pivot (``position``, Unity's
transform position) and rotation, while the package's scene file stores boxes; moving a box needs the
default pivot and yaw it was measured at. Developer tool, run once when the upstream data changes;
the package never reads ``../shared``. Output: ``mapless/data/scenes/ithor_v5_poses.json.gz``.

    python tools/build_pose_data.py ../shared/data/ithor
"""

from __future__ import annotations

import gzip
import io
import json
import sys
from pathlib import Path


def convert(shared: Path) -> dict:
    scenes = {}
    for path in sorted((shared / "layouts" / "metadata_v5").glob("FloorPlan*_physics.json")):
        objects = json.loads(path.read_text())
        poses = {}
        for meta in objects.values():
            if not (meta["pickupable"] or meta["moveable"]):
                continue
            p, r = meta["position"], meta["rotation"]
            poses[meta["name"]] = [round(float(v), 4) for v in (p["x"], p["y"], p["z"], r["y"])]
        scenes[path.name.removesuffix("_physics.json")] = dict(sorted(poses.items()))
    return {
        "format": "mapless-ithor-poses/1",
        "source": "pivot position (x, y, z) and yaw of every pickupable or moveable object of the AI2-THOR "
        ">=5.0.0 default layouts (Kajiih/rl_ai2thor @ 5907c98, MIT). See mapless/data/NOTICE.md.",
        "scenes": dict(sorted(scenes.items())),
    }


def main() -> None:
    shared = Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/ithor")
    text = json.dumps(convert(shared), sort_keys=True, separators=(",", ":")).encode()
    buffer = io.BytesIO()
    with gzip.GzipFile(fileobj=buffer, mode="wb", mtime=0, compresslevel=9) as f:
        f.write(text)
    out = Path(__file__).resolve().parents[1] / "mapless" / "data" / "scenes" / "ithor_v5_poses.json.gz"
    out.write_bytes(buffer.getvalue())
    print(f"wrote {out} ({len(buffer.getvalue())} bytes)")


if __name__ == "__main__":
    main()
