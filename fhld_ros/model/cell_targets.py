"""Ground truth of each anchor cell: the GT lane segment inside the r x r square.

Every GT polyline is clipped to the cell (Liang-Barsky, all cells x lanes x polyline pieces at
once). A lane's segment in a cell runs from where it first enters to where it last leaves;
its chord gives the bar: centre p_o (with the height interpolated there), length l, heading.
A cell is positive when some segment is at least min_segment_frac * r long; with several,
the one closest to the cell centre wins (paper). Everything is in normalised units.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from fhld_ros.model.anchors import AnchorGrid
from fhld_ros.model.config import FhldConfig
from fhld_ros.model.targets import LaneTargets


@dataclass
class CellTargets:
    label: Tensor    # (L, K) bool
    centre: Tensor   # (L, K, 2)
    length: Tensor   # (L, K)
    heading: Tensor  # (L, K, 2) unit vector
    z: Tensor        # (L, K) m


def point_segment_distance(p: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """Distance of points p to segments a-b (broadcast, last dim = coordinates)."""
    ab = b - a
    s = ((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)
    return (a + s.clamp(0, 1).unsqueeze(-1) * ab - p).norm(dim=-1)


def clip_lanes(centres: Tensor, half: float, lanes: Tensor) -> tuple[Tensor, ...]:
    """Chords of polylines lanes (M, P, 3) inside squares around centres (n, 2).

    Returns entry (n, M, 3), exit (n, M, 3) and inside (n, M) (the lane enters the square).
    """
    q0, d = lanes[:, :-1], lanes[:, 1:] - lanes[:, :-1]            # (M, S, 3)
    q0xy, dxy = q0[None, :, :, :2], d[None, :, :, :2]               # (1, M, S, 2)
    lo = (centres - half)[:, None, None, :]                         # (n, 1, 1, 2)
    hi = (centres + half)[:, None, None, :]
    parallel = dxy.abs() < 1e-12
    safe = torch.where(parallel, torch.ones_like(dxy), dxy)
    ta, tb = (lo - q0xy) / safe, (hi - q0xy) / safe
    in_slab = (q0xy >= lo) & (q0xy <= hi)
    inf = torch.full_like(ta, float('inf'))
    t_in = torch.where(parallel, torch.where(in_slab, -inf, inf), torch.minimum(ta, tb))
    t_out = torch.where(parallel, torch.where(in_slab, inf, -inf), torch.maximum(ta, tb))
    enter = t_in.amax(-1).clamp(min=0.0)
    leave = t_out.amin(-1).clamp(max=1.0)
    inside = leave > enter                                          # (n, M, S)
    pieces = inside.shape[-1]
    idx = torch.arange(pieces, device=lanes.device)
    first = torch.where(inside, idx, pieces).amin(-1).clamp(max=pieces - 1)  # (n, M)
    last = torch.where(inside, idx, -1).amax(-1).clamp(min=0)

    def point_at(piece: Tensor, t: Tensor) -> Tensor:
        m = torch.arange(lanes.shape[0], device=lanes.device).expand_as(piece)
        t_sel = t.gather(-1, piece.unsqueeze(-1)).squeeze(-1)
        return q0[m, piece] + t_sel.unsqueeze(-1) * d[m, piece]

    return point_at(first, enter), point_at(last, leave), inside.any(-1)


@torch.no_grad()
def cell_targets(anchors: AnchorGrid, gt: LaneTargets, cfg: FhldConfig) -> CellTargets:
    lanes, cells = anchors.shape
    device = anchors.centres.device
    n = lanes * cells
    label = torch.zeros(n, dtype=torch.bool, device=device)
    centre, z = torch.zeros(n, 2, device=device), torch.zeros(n, device=device)
    length, heading = torch.zeros(n, device=device), torch.zeros(n, 2, device=device)
    heading[:, 0] = 1.0
    flat = anchors.centres.reshape(-1, 2)
    batch = anchors.batch.unsqueeze(1).expand(-1, cells).reshape(-1)
    counts = gt.counts()
    for item in torch.unique(batch).tolist():
        if counts[item] == 0:
            continue
        sel = (batch == item).nonzero(as_tuple=True)[0]
        entry, leave, inside = clip_lanes(flat[sel], cfg.cell_norm / 2,
                                          gt.points[item, :counts[item]])
        chord = leave[..., :2] - entry[..., :2]
        seg_len = chord.norm(dim=-1)                                 # (n, M)
        ok = inside & (seg_len >= cfg.min_segment_frac * cfg.cell_norm)
        dist = point_segment_distance(flat[sel, None], entry[..., :2], leave[..., :2])
        best = torch.where(ok, dist, torch.full_like(dist, float('inf'))).argmin(-1)
        rows = torch.arange(len(sel), device=device)
        first, last, best_len = entry[rows, best], leave[rows, best], seg_len[rows, best]
        mid = (first + last) / 2
        label[sel] = ok.any(-1)
        centre[sel], z[sel], length[sel] = mid[:, :2], mid[:, 2], best_len
        heading[sel] = chord[rows, best] / best_len.clamp_min(1e-9).unsqueeze(-1)
    shape = (lanes, cells)
    return CellTargets(label.reshape(shape), centre.reshape(*shape, 2), length.reshape(shape),
                       heading.reshape(*shape, 2), z.reshape(shape))
