"""`fhld eval PRED_BAG GT_BAG`: score predicted /lanes against /lanes_gt (docs/design.md §6).

Every /lanes message is one frame. Its GT is the latest /lanes_gt message at or before its
stamp (else the first one, if it comes less than GT_LEAD_NS later). Both are brought into that
frame's window frame, derived from the bev_window outline (bev.py corner order: rear-right,
front-right, front-left, rear-left, back to the first; so corner 0 -> 1 is forward, 0 -> 3 is
left), clipped to the window square and scored with fhld_ros.evaluation.metrics. An outline that
is no square but a closed simple polygon (fhld autolabel: the ground its camera sees) is the
region itself: lanes are clipped to it in top view, in a frame whose x axis points into it from
its closing edge (window_region). Counts are summed over frames; percentages come last.

--per-frame and --plots follow bagio's output rule: an existing file is refused unless
--overwrite (which replaces only a regular file), and no output may be, contain or lie inside
PRED_BAG or GT_BAG. --plots DIR may exist: the rule applies to each PNG written into it.
"""
from __future__ import annotations

import argparse
import csv
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from fhld_ros.bagio import (
    BagError,
    bag_topics,
    check_file_output,
    read_lane_sets,
    write_file_atomically,
)
from fhld_ros.errors import ConfigError
from fhld_ros.evaluation import metrics
from fhld_ros.evaluation.window_region import clip_polyline_to_polygon, window_region

MARKER_ARRAY = 'visualization_msgs/msg/MarkerArray'
GT_LEAD_NS = 1_000_000_000  # a /lanes message may precede the first /lanes_gt by this much


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('pred_bag', metavar='PRED_BAG', help='bag with predicted /lanes')
    parser.add_argument('gt_bag', metavar='GT_BAG', help='bag with /lanes_gt (e.g. from simulate)')
    parser.add_argument('--json', action='store_true', help='print one JSON object last')
    parser.add_argument('--per-frame', metavar='CSV', help='write per-frame counts and scores')
    parser.add_argument('--plots', metavar='DIR', help='PNGs of the worst frames (by F1@10)')
    parser.add_argument('--worst', type=int, default=5, metavar='N',
                        help='how many frames --plots draws (default 5)')
    parser.add_argument('--once-official', action='store_true',
                        help="ONCE metric as the authors' released evaluator computes it")
    parser.add_argument('--score-thresh', type=float, default=0.1, metavar='T',
                        help='--once-official keeps predictions with score > T (default 0.1)')
    parser.add_argument('--pred-topic', default='/lanes', help='default /lanes')
    parser.add_argument('--gt-topic', default='/lanes_gt', help='default /lanes_gt')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace existing --per-frame / --plots files (regular files only)')


@dataclass
class Frame:
    """Scores of one /lanes message, lanes in its window frame (for plots)."""

    index: int
    stamp_ns: int
    gt_stamp_ns: int
    half_size: float
    pred: list[np.ndarray]
    gt: list[np.ndarray]
    point: metrics.PointCounts
    once: metrics.LaneCounts
    outline: np.ndarray | None = None  # (M, 2) closed, window frame: a polygon window's shape


def _read_lanesets(path: str, topic: str, role: str) -> list[Any]:
    """LaneSets of every message on `topic`; ConfigError for unreadable bags or missing topics."""
    try:
        topics = bag_topics(path)
        if topic not in topics:
            have = ', '.join(sorted(topics)) or 'nothing'
            raise ConfigError(f'{role} bag {path} has no topic {topic} (it has: {have})')
        if topics[topic] != MARKER_ARRAY:
            raise ConfigError(f'{role} bag {path}: {topic} is {topics[topic]}, not {MARKER_ARRAY}')
        sets = read_lane_sets(path, topic)
    except BagError as exc:
        raise ConfigError(str(exc)) from exc
    if not sets:
        raise ConfigError(f'{role} bag {path} has no messages on {topic}')
    return sets


def _pair_gt(preds: list[Any], gts: list[Any], args: argparse.Namespace) -> list[Any]:
    """The /lanes_gt message of every /lanes message (see module doc), checking frames."""
    gt_stamps = np.array([g.stamp_ns for g in gts], dtype=np.int64)
    order = np.argsort(gt_stamps, kind='stable')
    gt_stamps = gt_stamps[order]
    pred_stamps = np.array([p.stamp_ns for p in preds], dtype=np.int64)
    idx = np.searchsorted(gt_stamps, pred_stamps, side='right') - 1
    early = idx < 0
    too_early = early & (gt_stamps[0] - pred_stamps > GT_LEAD_NS)
    if too_early.any():
        raise ConfigError(
            f'{int(too_early.sum())} of {len(preds)} {args.pred_topic} messages come more than '
            f'{GT_LEAD_NS / 1e9:g} s before the first {args.gt_topic} message '
            f'({pred_stamps.min() / 1e9:.3f} s vs {gt_stamps[0] / 1e9:.3f} s): '
            f'{args.pred_bag} and {args.gt_bag} do not seem to be the same drive')
    paired = [gts[order[max(i, 0)]] for i in idx]
    for k, (pred, gt) in enumerate(zip(preds, paired)):
        if gt.lanes and pred.frame_id != gt.frame_id:
            raise ConfigError(f'frame mismatch: {args.pred_topic} message {k} is in '
                              f'"{pred.frame_id}" but its {args.gt_topic} is in "{gt.frame_id}"')
    return paired


def _to_window(lanes: list[np.ndarray], origin: np.ndarray, rot: np.ndarray) -> list[np.ndarray]:
    return [(np.asarray(lane, dtype=np.float64) - origin) @ rot for lane in lanes]


def _score_frame(k: int, pred: Any, gt: Any, args: argparse.Namespace) -> Frame:
    origin, rot, half, polygon = window_region(pred.window_outline)

    def clip(lane: np.ndarray) -> list[np.ndarray]:
        if polygon is None:
            return metrics.clip_polyline_to_square(lane, half)
        return clip_polyline_to_polygon(lane, polygon)
    gt_lanes = [part for lane in _to_window(gt.lanes, origin, rot) for part in clip(lane)]
    pred_lanes, scores = [], []
    for lane, conf in zip(_to_window(pred.lanes, origin, rot), pred.confidences):
        pieces = clip(lane)
        pred_lanes += pieces
        scores += [float(conf)] * len(pieces)  # a split lane keeps its confidence
    point = metrics.point_counts(pred_lanes, gt_lanes)
    if args.once_official:
        once = metrics.once_counts_official(pred_lanes, scores, gt_lanes, args.score_thresh)
    else:
        once = metrics.once_counts(pred_lanes, gt_lanes, half)
    ring = None if polygon is None else np.vstack([polygon, polygon[:1]])
    return Frame(k, pred.stamp_ns, gt.stamp_ns, half, pred_lanes, gt_lanes, point, once, ring)


def evaluate_bags(args: argparse.Namespace) -> list[Frame]:
    """Per-frame scores of PRED_BAG against GT_BAG; ConfigError on bad input."""
    preds = _read_lanesets(args.pred_bag, args.pred_topic, 'prediction')
    gts = _read_lanesets(args.gt_bag, args.gt_topic, 'ground-truth')
    missing = [k for k, p in enumerate(preds) if p.window_outline is None]
    if missing:
        raise ConfigError(f'{len(missing)} of {len(preds)} {args.pred_topic} messages have no '
                          f'bev_window marker (first: message {missing[0]}, stamp '
                          f'{preds[missing[0]].stamp_ns} ns); cannot tell which region was '
                          'searched')
    frames = []
    for k, (pred, gt) in enumerate(zip(preds, _pair_gt(preds, gts, args))):
        try:
            frames.append(_score_frame(k, pred, gt, args))
        except ValueError as exc:
            raise ConfigError(f'{args.pred_topic} message {k}: bev_window {exc}') from exc
    return frames


def summary(frames: list[Frame], official: bool = False) -> dict[str, Any]:
    """The JSON object of §4: frames, point {P@10 ...}, once {P, R, F1, CD}."""
    point = sum((f.point for f in frames), metrics.PointCounts())
    once = sum((f.once for f in frames), metrics.LaneCounts(official=official))
    return {'frames': len(frames), 'point': point.scores(), 'once': once.scores(),
            'once_mode': 'official' if official else 'paper'}


def _print_table(result: dict[str, Any], args: argparse.Namespace) -> None:
    point, once = result['point'], result['once']
    print(f'fhld eval: {result["frames"]} frames, {args.pred_topic} from {args.pred_bag}, '
          f'{args.gt_topic} from {args.gt_bag}')
    print(f'{"FHLD point metric":<26}{"precision":>10}{"recall":>10}{"F1":>10}')
    for cm in ('10', '30'):
        print(f'{"  within " + cm + " cm":<26}{point["P@" + cm]:>10.2f}{point["R@" + cm]:>10.2f}'
              f'{point["F1@" + cm]:>10.2f}')
    mode = ("released evaluator, score > " + f'{args.score_thresh:g}' if args.once_official
            else 'paper')
    print(f'ONCE-3DLanes ({mode})')
    print(f'{"":<26}{"precision":>10}{"recall":>10}{"F1":>10}{"CD (m)":>10}')
    print(f'{"  IoU>=0.3, CD<=0.3 m" if not args.once_official else "  CD<0.3 m":<26}'
          f'{once["P"]:>10.2f}{once["R"]:>10.2f}{once["F1"]:>10.2f}{once["CD"]:>10.3f}')


def _frame_row(f: Frame) -> dict[str, Any]:
    s = f.point.scores()
    return {'frame': f.index, 'stamp_ns': f.stamp_ns, 'gt_stamp_ns': f.gt_stamp_ns,
            'pred_lanes': len(f.pred), 'gt_lanes': len(f.gt),
            'pred_points': f.point.n_pred, 'gt_points': f.point.n_gt,
            'pred_hits@10': int(f.point.pred_hits[0]), 'gt_hits@10': int(f.point.gt_hits[0]),
            'pred_hits@30': int(f.point.pred_hits[1]), 'gt_hits@30': int(f.point.gt_hits[1]),
            **{k: round(v, 3) for k, v in s.items()},
            'once_pred': f.once.n_pred, 'once_gt': f.once.n_gt, 'once_tp': f.once.tp,
            'once_cd_sum': round(f.once.cd_sum, 5)}


def write_per_frame(frames: list[Frame], path: str) -> None:
    rows = [_frame_row(f) for f in frames]

    def write(tmp: Path) -> None:
        with open(tmp, 'w', newline='') as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    write_file_atomically(path, write)


def _inputs(args: argparse.Namespace) -> dict[str, str]:
    return {'PRED_BAG': args.pred_bag, 'GT_BAG': args.gt_bag}


def check_outputs(args: argparse.Namespace) -> None:
    """ConfigError unless --per-frame and --plots may be written (bagio's rule); before the
    bags are read, so a refused output costs no scoring."""
    if args.per_frame:
        check_file_output(args.per_frame, args.overwrite, _inputs(args), '--per-frame')
    if args.plots:
        plots = Path(args.plots)
        if plots.is_dir():  # its PNGs are checked when plot_worst knows their names
            return
        if plots.exists() or plots.is_symlink():
            raise ConfigError(f'--plots {plots} exists and is not a directory')
        check_file_output(plots, False, _inputs(args), '--plots')


def draw_top_view(path: Path, gt: Sequence[np.ndarray], pred: Sequence[np.ndarray],
                  half: float, title: str, background: np.ndarray | None = None,
                  outline: np.ndarray | None = None) -> None:
    """A PNG of window-frame lanes seen from above, forward up and left to the left: GT (green,
    wide) under predictions (red), the ego, and the window outline (the square, else a closed
    (M, 2) polygon, then without the ego) or a (H, W) raster behind."""
    fig = Figure(figsize=(7, 7))  # no pyplot: no GUI backend, no global figure registry
    ax = fig.subplots()
    if background is None:
        ring = outline if outline is not None else \
            np.array([[-half, -half], [half, -half], [half, half], [-half, half], [-half, -half]])
        ax.plot(ring[:, 1], ring[:, 0], color='0.6', lw=1)
    else:  # raster rows: y, cols: x -> image rows: x forward (up), cols: y left (left)
        ax.imshow(np.sqrt(background.T[::-1, ::-1]), cmap='gray', vmax=0.8,
                  extent=(half, -half, -half, half))
    for i, lane in enumerate(gt):
        ax.plot(lane[:, 1], lane[:, 0], color='lime', lw=5, alpha=0.45,
                label='ground truth' if i == 0 else None)
    for i, lane in enumerate(pred):
        ax.plot(lane[:, 1], lane[:, 0], color='red', lw=1.3,
                label='detected' if i == 0 else None)
    if outline is None:  # a polygon's frame is centred on its bounding box, not on the ego
        ax.plot([0], [0], marker='^', color='tab:cyan', ms=9, label='ego')
    ax.set_xlim(half, -half)
    ax.set_ylim(-half, half)
    ax.set_aspect('equal')
    ax.set_xlabel('y (m, left)')
    ax.set_ylabel('x (m, forward)')
    ax.set_title(title, fontsize=9)
    ax.legend(loc='lower right', fontsize=8, framealpha=0.9)
    fig.savefig(path, dpi=110, bbox_inches='tight')


def plot_worst(frames: list[Frame], out_dir: str, n: int, overwrite: bool = False,
               inputs: dict[str, str] | None = None) -> list[Path]:
    """Top-view PNGs of the n frames with the lowest F1@10 (frames with lanes only). Every
    PNG is checked (bagio.check_file_output: overwrite, inputs) before the first is written."""
    scored = [f for f in frames if f.point.n_gt or f.point.n_pred]
    scored.sort(key=lambda f: (f.point.scores()['F1@10'], f.index))
    out = Path(out_dir)
    out.mkdir(exist_ok=True)
    worst = [(f, out / f'frame_{f.index:05d}.png') for f in scored[:max(n, 0)]]
    for _, path in worst:
        check_file_output(path, overwrite, inputs, '--plots')
    for f, path in worst:
        s = f.point.scores()
        title = (f'frame {f.index}  t={f.stamp_ns / 1e9:.3f} s\n'
                 f'@10 cm P {s["P@10"]:.1f} R {s["R@10"]:.1f} F1 {s["F1@10"]:.1f}   '
                 f'@30 cm F1 {s["F1@30"]:.1f}')
        write_file_atomically(path, lambda tmp, f=f, title=title: draw_top_view(
            tmp, f.gt, f.pred, f.half_size, title, outline=f.outline))
    return [path for _, path in worst]


def run(args: argparse.Namespace) -> int:
    check_outputs(args)
    frames = evaluate_bags(args)
    result = summary(frames, official=args.once_official)
    if args.per_frame:
        write_per_frame(frames, args.per_frame)
    if args.plots:
        written = plot_worst(frames, args.plots, args.worst, args.overwrite, _inputs(args))
        print(f'wrote {len(written)} plot(s) of the worst frames to {args.plots}')
    _print_table(result, args)
    if args.json:
        print(json.dumps(result))
    return 0
