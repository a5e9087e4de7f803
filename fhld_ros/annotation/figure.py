"""A picture of one autolabelled image: the 3D lanes projected over the camera image beside the
2D labels they came from, and the same lanes from above over the ground returns."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from fhld_ros.camera.calibration import CameraCalibration
from fhld_ros.camera.labels2d import ImageLabels

COLOURS = ('tab:red', 'tab:orange', 'gold', 'tab:green', 'tab:cyan', 'tab:blue', 'tab:purple',
           'tab:pink')


def draw_autolabel(path: str | Path, calib: CameraCalibration, labels: ImageLabels,
                   rgb: np.ndarray | None, lanes_camera: list[np.ndarray], ids: list[int],
                   ground_camera: np.ndarray, ground_contrast: np.ndarray, title: str) -> None:
    """lanes_camera and ground_camera are in the camera optical frame (x right, z forward)."""
    fig = Figure(figsize=(14, 5.6))
    ax_img, ax_top = fig.subplots(1, 2, gridspec_kw={'width_ratios': [1.7, 1]})
    if rgb is not None:
        ax_img.imshow(rgb)
    for lane in labels.lanes:
        ax_img.plot(lane.uv[:, 0], lane.uv[:, 1], color='white', lw=4, alpha=0.5)
    for lane, lane_id in zip(lanes_camera, ids):
        uv, _, ok = calib.project_camera(lane)
        ax_img.plot(uv[ok, 0], uv[ok, 1], '.-', color=COLOURS[lane_id % len(COLOURS)], lw=1.2,
                    ms=3)
    ax_img.set_xlim(0, calib.width)
    ax_img.set_ylim(calib.height, 0)
    ax_img.set_axis_off()
    ax_img.set_title('2D labels (white) and the 3D lanes projected back (colour)', fontsize=9)

    reach = max(20.0, float(np.percentile(ground_camera[:, 2], 98))) if ground_camera.size \
        else 40.0
    near = ground_camera[:, 2] < reach
    ax_top.scatter(ground_camera[near, 0], ground_camera[near, 2], s=1.5,
                   c=np.clip(ground_contrast[near], 0, 6), cmap='gray', vmin=0, vmax=6,
                   linewidths=0)
    for lane, lane_id in zip(lanes_camera, ids):
        ax_top.plot(lane[:, 0], lane[:, 2], color=COLOURS[lane_id % len(COLOURS)], lw=1.5)
    ax_top.plot([0], [0], marker='^', color='tab:cyan', ms=9)
    ax_top.set_xlim(-reach / 2, reach / 2)
    ax_top.set_ylim(0, reach)
    ax_top.set_aspect('equal')
    ax_top.set_facecolor('black')
    ax_top.set_xlabel('camera x (m, right)')
    ax_top.set_ylabel('camera z (m, forward)')
    ax_top.set_title('3D lanes from above over the ground returns (brightness: paint contrast)',
                     fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=90, bbox_inches='tight')
