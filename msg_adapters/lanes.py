"""Lanes <-> visualization_msgs/MarkerArray and nav_msgs/Path (docs/design.md §3, fixed).

A /lanes message is: one DELETEALL marker (ns `lanes`), one LINE_STRIP per lane (ns `lanes`,
id stable per lane, colour alpha = confidence, text `conf=0.93`), and one LINE_STRIP in ns
`bev_window` with the closed 5-point outline of the searched window.
"""
from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from msg_adapters.cdr import ENCAPSULATION_CDR_LE, CdrWriter
from msg_adapters.family import MessageFamily, stamp_to_ns

LANES_NS = 'lanes'
WINDOW_NS = 'bev_window'
LINE_STRIP = 4
ADD = 0
DELETEALL = 3
LINE_WIDTH_M = 0.15
# Distinct, colour-blind friendly hues (Okabe-Ito); a lane keeps its colour through its id.
PALETTE = np.array([[0.90, 0.62, 0.00], [0.34, 0.71, 0.91], [0.00, 0.62, 0.45],
                    [0.94, 0.89, 0.26], [0.00, 0.45, 0.70], [0.84, 0.37, 0.00],
                    [0.80, 0.47, 0.65]])


@dataclass
class LaneSet:
    """The lanes of one MarkerArray, in its frame."""

    stamp_ns: int
    frame_id: str
    lanes: list[np.ndarray] = field(default_factory=list)  # (K, 3) float64 each
    confidences: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    window_outline: np.ndarray | None = None  # (5, 3) closed polygon


@dataclass(frozen=True)
class _Strip:
    """One LINE_STRIP marker of a /lanes message."""

    ns: str
    marker_id: int
    xyz: np.ndarray  # (K, 3) float64
    rgba: tuple[float, float, float, float]
    text: str = ''


def _strips(lanes: Sequence[np.ndarray], confidences: Sequence[float], ids: Sequence[int],
            window_outline: np.ndarray | None) -> list[_Strip]:
    """The LINE_STRIPs of a /lanes message (after its DELETEALL marker), in order."""
    if not len(lanes) == len(confidences) == len(ids):
        raise ValueError(f'{len(lanes)} lanes, {len(confidences)} confidences and {len(ids)} '
                         'ids must match')
    strips = []
    for lane, conf, lane_id in zip(lanes, confidences, ids):
        conf = float(np.clip(conf, 0.0, 1.0))
        r, g, b = (float(v) for v in PALETTE[int(lane_id) % len(PALETTE)])
        strips.append(_Strip(LANES_NS, int(lane_id), np.asarray(lane, dtype=np.float64),
                             (r, g, b, conf), f'conf={conf:.2f}'))
    if window_outline is not None:
        outline = np.asarray(window_outline, dtype=np.float64)
        if outline.shape != (5, 3):
            raise ValueError(f'window outline must be (5, 3), got {outline.shape}')
        strips.append(_Strip(WINDOW_NS, 0, outline, (0.6, 0.6, 0.6, 0.8)))
    return strips


def _identity_pose(family: MessageFamily) -> Any:
    return family.new('geometry_msgs/msg/Pose',
                      orientation=family.new('geometry_msgs/msg/Quaternion', w=1.0))


def _line_strip(family: MessageFamily, header: Any, strip: _Strip) -> Any:
    r, g, b, a = strip.rgba
    points = [family.new('geometry_msgs/msg/Point', x=x, y=y, z=z)
              for x, y, z in strip.xyz.tolist()]
    return family.new(
        'visualization_msgs/msg/Marker', header=header, ns=strip.ns, id=strip.marker_id,
        type=LINE_STRIP, action=ADD, pose=_identity_pose(family),
        scale=family.new('geometry_msgs/msg/Vector3', x=LINE_WIDTH_M),
        color=family.new('std_msgs/msg/ColorRGBA', r=r, g=g, b=b, a=a),
        points=points, text=strip.text)


def lanes_to_marker_array(family: MessageFamily, header: Any, lanes: Sequence[np.ndarray],
                          confidences: Sequence[float], ids: Sequence[int],
                          window_outline: np.ndarray | None = None) -> Any:
    """MarkerArray of the §3 contract; `window_outline` (5, 3) adds the bev_window strip."""
    strips = _strips(lanes, confidences, ids, window_outline)
    markers = [family.new('visualization_msgs/msg/Marker', header=header, ns=LANES_NS,
                          action=DELETEALL, pose=_identity_pose(family))]
    markers += [_line_strip(family, header, strip) for strip in strips]
    return family.new('visualization_msgs/msg/MarkerArray', markers=markers)


def lanes_to_marker_array_cdr(stamp_ns: int, frame_id: str, lanes: Sequence[np.ndarray],
                              confidences: Sequence[float], ids: Sequence[int],
                              window_outline: np.ndarray | None = None) -> bytes:
    """lanes_to_marker_array's message as CDR bytes (what rclpy and rosbag2 send and store)."""
    strips = _strips(lanes, confidences, ids, window_outline)
    out = CdrWriter()
    out.pack('I', len(strips) + 1)
    _marker_cdr(out, stamp_ns, frame_id, _Strip(LANES_NS, 0, np.zeros((0, 3)), (0, 0, 0, 0)),
                DELETEALL)
    for strip in strips:
        _marker_cdr(out, stamp_ns, frame_id, strip, ADD)
    return out.getvalue()


def _marker_cdr(out: CdrWriter, stamp_ns: int, frame_id: str, strip: _Strip, action: int
                ) -> None:
    """visualization_msgs/Marker: a LINE_STRIP (ADD) or DELETEALL, every other field empty."""
    out.header(stamp_ns, frame_id)
    out.string(strip.ns)
    out.pack('iii', strip.marker_id, LINE_STRIP if action == ADD else 0, action)
    out.pack('7d', 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # pose: identity
    out.pack('3d', LINE_WIDTH_M if action == ADD else 0.0, 0.0, 0.0)  # scale
    out.pack('4f', *strip.rgba)
    out.pack('iI?', 0, 0, False)  # lifetime, frame_locked
    out.pack('I', len(strip.xyz))
    out.array(strip.xyz, '<f8')  # points
    out.pack('I', 0)  # colors
    out.string('')  # texture_resource
    out.header(0, '')  # texture: sensor_msgs/CompressedImage
    out.string('')
    out.pack('I', 0)
    out.pack('I', 0)  # uv_coordinates
    out.string(strip.text)
    out.string('')  # mesh_resource
    out.string('')  # mesh_file: visualization_msgs/MeshFile
    out.pack('I?', 0, False)  # its data, then mesh_use_embedded_materials


def unique_marker_ids(ids: Sequence[int]) -> list[int]:
    """Marker ids for lanes that may share a line id (pieces of one line): the line's id, and
    id + 1000 * k for its k-th further piece."""
    seen: dict[int, int] = {}
    out = []
    for i in ids:
        k = seen.get(int(i), 0)
        seen[int(i)] = k + 1
        out.append(int(i) + 1000 * k)
    return out


def _confidence(marker: Any) -> float:
    text = str(marker.text)
    if text.startswith('conf='):
        try:
            return float(text[5:])
        except ValueError:
            pass
    return float(marker.color.a)


def marker_array_to_lanes(msg: Any) -> LaneSet:
    """Lanes, confidences, ids and window outline of a /lanes (or /lanes_gt) MarkerArray."""
    markers = list(msg.markers)
    if not markers:
        return LaneSet(stamp_ns=0, frame_id='')
    head = markers[0].header
    result = LaneSet(stamp_ns=stamp_to_ns(head.stamp), frame_id=str(head.frame_id))
    lanes, confidences, ids = [], [], []
    for marker in markers:
        if int(marker.action) == DELETEALL or int(marker.type) != LINE_STRIP:
            continue
        xyz = np.array([(p.x, p.y, p.z) for p in marker.points], dtype=np.float64).reshape(-1, 3)
        if marker.ns == WINDOW_NS:
            result.window_outline = xyz
            continue
        lanes.append(xyz)
        confidences.append(_confidence(marker))
        ids.append(int(marker.id))
    result.lanes = lanes
    result.confidences = np.asarray(confidences, dtype=np.float64)
    result.ids = np.asarray(ids, dtype=np.int64)
    return result


def _path_poses(lane: np.ndarray | None) -> np.ndarray:
    """(K, 7) x, y, z, qx, qy, qz, qw: a lane's points, each heading along the lane (the last
    keeps the last segment's heading)."""
    if lane is None or len(lane) == 0:
        return np.zeros((0, 7))
    xyz = np.asarray(lane, dtype=np.float64)
    step = np.diff(xyz[:, :2], axis=0) if len(xyz) > 1 else np.zeros((0, 2))
    step = np.vstack([step, step[-1:] if len(step) else [[1.0, 0.0]]])
    half = np.arctan2(step[:, 1], step[:, 0]) / 2
    zeros = np.zeros(len(xyz))
    return np.column_stack([xyz, zeros, zeros, np.sin(half), np.cos(half)])


def lane_to_path(family: MessageFamily, header: Any, lane: np.ndarray | None) -> Any:
    """nav_msgs/Path through a lane's points, each pose heading along the lane; empty if None."""
    poses = []
    for x, y, z, _, _, qz, qw in _path_poses(lane).tolist():
        pose = family.new(
            'geometry_msgs/msg/Pose',
            position=family.new('geometry_msgs/msg/Point', x=x, y=y, z=z),
            orientation=family.new('geometry_msgs/msg/Quaternion', z=qz, w=qw))
        poses.append(family.new('geometry_msgs/msg/PoseStamped', header=header, pose=pose))
    return family.new('nav_msgs/msg/Path', header=header, poses=poses)


def lane_to_path_cdr(stamp_ns: int, frame_id: str, lane: np.ndarray | None) -> bytes:
    """lane_to_path's message as CDR bytes."""
    out = CdrWriter()
    out.header(stamp_ns, frame_id)
    poses = _path_poses(lane)
    out.pack('I', len(poses))
    if len(poses) == 0:
        return out.getvalue()
    out.header(stamp_ns, frame_id)  # geometry_msgs/PoseStamped
    out.array(poses[0], '<f8')
    # The poses end 8-aligned, so every later PoseStamped has the same bytes before its pose.
    head = CdrWriter()
    head.header(stamp_ns, frame_id)
    head.align(8)
    prefix = np.frombuffer(head.getvalue()[len(ENCAPSULATION_CDR_LE):], dtype=np.uint8)
    rows = np.empty((len(poses) - 1, prefix.size + 56), dtype=np.uint8)
    rows[:, :prefix.size] = prefix
    rows[:, prefix.size:] = np.ascontiguousarray(poses[1:], dtype='<f8').view(np.uint8)
    out.array(rows, 'u1')
    return out.getvalue()


def marker_array_stamp_ns(raw: bytes) -> int:
    """Header stamp of the first marker of a CDR-serialised MarkerArray, without decoding it."""
    if len(raw) < 8 or raw[1] not in (0, 1):
        raise ValueError('not a CDR-serialised MarkerArray')
    order = '<' if raw[1] == 1 else '>'  # encapsulation: CDR little / big endian
    if struct.unpack_from(f'{order}I', raw, 4)[0] == 0 or len(raw) < 16:
        raise ValueError('MarkerArray without markers')
    sec, nanosec = struct.unpack_from(f'{order}iI', raw, 8)
    return sec * 1_000_000_000 + nanosec
