"""Ground-truth lane polylines cut to a region: the window square or a disc around the car."""
from __future__ import annotations

import numpy as np


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def clip_to_square(lines: list[np.ndarray], half: float, min_length: float = 0.2
                   ) -> tuple[list[np.ndarray], list[int]]:
    """Parts of (K, 3) polylines inside the square |x|, |y| < half (window frame).

    Each segment is clipped exactly (Liang-Barsky); consecutive inside segments are joined and a
    line that leaves and re-enters gives several pieces. Returns pieces and their source index.
    """
    out, src = [], []
    for index, line in enumerate(lines):
        if line.shape[0] < 2:
            continue
        p0, p1 = line[:-1], line[1:]
        delta = p1 - p0
        lo = np.zeros(len(p0))
        hi = np.ones(len(p0))
        for axis in (0, 1):
            for sign in (-1.0, 1.0):  # boundary sign * x <= half
                num = half - sign * p0[:, axis]
                den = sign * delta[:, axis]
                with np.errstate(divide='ignore', invalid='ignore'):
                    t = num / den
                lo = np.where(den < 0, np.maximum(lo, t), lo)
                hi = np.where(den > 0, np.minimum(hi, t), hi)
                lo = np.where((den == 0) & (num < 0), 2.0, lo)  # parallel and outside
        seg = np.flatnonzero(lo < hi)
        if seg.size == 0:
            continue
        start = p0[seg] + lo[seg, None] * delta[seg]
        end = p0[seg] + hi[seg, None] * delta[seg]
        # a piece continues while segments follow each other through full vertices
        joined = (np.diff(seg) == 1) & (hi[seg[:-1]] >= 1.0 - 1e-12) & (lo[seg[1:]] <= 1e-12)
        for part in np.split(np.arange(seg.size), np.flatnonzero(~joined) + 1):
            piece = np.vstack([start[part[:1]], end[part]])
            steps = np.linalg.norm(np.diff(piece[:, :2], axis=0), axis=1)
            piece = piece[np.concatenate([[True], steps > 1e-9])]
            if piece.shape[0] >= 2 and steps.sum() >= min_length:
                out.append(piece)
                src.append(index)
    return out, src


def crop_to_disc(lines: list[np.ndarray], centre: np.ndarray, radius: float
                 ) -> tuple[list[np.ndarray], list[int]]:
    """Vertex runs of polylines within radius of centre (xy); keeps each run's line index."""
    out, src = [], []
    for index, line in enumerate(lines):
        inside = np.hypot(line[:, 0] - centre[0], line[:, 1] - centre[1]) <= radius
        for a, b in runs(inside):
            if b - a >= 2:
                out.append(line[a:b])
                src.append(index)
    return out, src
