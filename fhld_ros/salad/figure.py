"""Lanes drawn over the image they were detected in: predictions in red, ground truth (when
there is one) in green, projected with the image's own intrinsics."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

MIN_DEPTH_M = 0.5
PRED_COLOUR = (230, 40, 40)
GT_COLOUR = (40, 220, 60)


def project(lane: np.ndarray, k: np.ndarray) -> np.ndarray:
    """(M, 2) pixels of the lane's points in front of the camera (optical frame)."""
    pts = lane[lane[:, 2] > MIN_DEPTH_M]
    return (pts @ k.T)[:, :2] / pts[:, 2:3]


def draw_lanes(image: np.ndarray, k: np.ndarray, lanes: list[np.ndarray],
               gt: list[np.ndarray] | None = None, path: str | Path | None = None,
               width: int = 3) -> Image.Image:
    """The image with the lanes drawn; saved to path when given."""
    canvas = Image.fromarray(np.asarray(image)).convert('RGB')
    draw = ImageDraw.Draw(canvas)
    scaled = max(1, round(width * canvas.width / 960))
    for group, colour in ((gt or [], GT_COLOUR), (lanes, PRED_COLOUR)):
        for lane in group:
            px = project(np.asarray(lane, dtype=np.float64), np.asarray(k, dtype=np.float64))
            if len(px) >= 2:
                draw.line([tuple(p) for p in px], fill=colour, width=scaled)
    if path is not None:
        canvas.save(path)
    return canvas
