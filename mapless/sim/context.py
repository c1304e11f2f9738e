"""The context vector's observable part, shared by every scene backend.

MJOLNIR's definition per category: ``[1, mean of the boxes' x1/x2, mean of y1/y2, union-box area]``,
coordinates normalised by the frame size; rows of categories not in view are zero.
"""

from __future__ import annotations

import numpy as np

IMAGE_SIZE = 300


def context_from_boxes(
    inst_category: np.ndarray, boxes: np.ndarray, n_categories: int, image_size: int = IMAGE_SIZE
) -> np.ndarray:
    """MJOLNIR context rows ``[C, 4]`` of one pose from its in-view entries: in view, mean of the
    boxes' x1/x2 and y1/y2 (normalised), union-box area / image_size². Entries with category -1
    are ignored. Used by the simulator and the offline reader alike, so exported scenes read back equal."""
    out = np.zeros((n_categories, 4), dtype=np.float32)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    for c in np.unique(inst_category[inst_category >= 0]):
        b = boxes[inst_category == c] / image_size
        out[c, 0] = 1.0
        out[c, 1] = b[:, [0, 2]].mean()
        out[c, 2] = b[:, [1, 3]].mean()
        out[c, 3] = (b[:, 2].max() - b[:, 0].min()) * (b[:, 3].max() - b[:, 1].min())
    return out
