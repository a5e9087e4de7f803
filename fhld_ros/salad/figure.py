"""Lanes drawn over the image they were detected in: predictions in red, ground truth (when
there is one) in green, projected with the image's own intrinsics and lens distortion."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from fhld_ros.camera.calibration import distort
from fhld_ros.camera.lens import Lens

MIN_DEPTH_M = 0.5
PRED_COLOUR = (230, 40, 40)
GT_COLOUR = (40, 220, 60)


def project(lane: np.ndarray, k: np.ndarray, distortion: Lens | np.ndarray | None = None
            ) -> np.ndarray:
    """(M, 2) pixels of the lane's points in front of the camera (optical frame)."""
    pts = lane[lane[:, 2] > MIN_DEPTH_M]
    x, y = pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2]
    x, y = distort(x, y, distortion)
    return np.column_stack([k[0, 0] * x + k[0, 1] * y + k[0, 2], k[1, 1] * y + k[1, 2]])


def draw_lanes(image: np.ndarray, k: np.ndarray, lanes: list[np.ndarray],
               gt: list[np.ndarray] | None = None, path: str | Path | None = None,
               width: int = 3, distortion: np.ndarray | None = None) -> Image.Image:
    """The image with the lanes drawn; saved to path when given."""
    canvas = Image.fromarray(np.asarray(image)).convert('RGB')
    draw = ImageDraw.Draw(canvas)
    scaled = max(1, round(width * canvas.width / 960))
    for group, colour in ((gt or [], GT_COLOUR), (lanes, PRED_COLOUR)):
        for lane in group:
            px = project(np.asarray(lane, dtype=np.float64), np.asarray(k, dtype=np.float64),
                         distortion)
            if len(px) >= 2:
                draw.line([tuple(p) for p in px], fill=colour, width=scaled)
    if path is not None:
        canvas.save(path)
    return canvas
