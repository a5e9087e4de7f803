"""Ground-truth 2D lane labels of a simulated camera image: the scene's GT lines projected
with the camera's true pose, cut where they leave the image, lie beyond LABEL_RANGE_M or are
hidden behind something nearer in the rendered depth (docs/annotation.md)."""
from __future__ import annotations

import argparse

import numpy as np
from PIL import Image, ImageDraw

from fhld_ros.camera.calibration import CameraCalibration
from fhld_ros.camera.labels2d import ImageLabels, LaneLabel2D
from fhld_ros.geometry import resample_polyline
from fhld_ros.sim.camera import CameraImage, SimCamera
from fhld_ros.sim.gt_lines import crop_to_disc, runs
from fhld_ros.sim.simulator import Simulator

LABEL_STEP_M = 0.25  # GT lines are resampled this finely before projection
LABEL_RANGE_M = 60.0  # farther points (camera depth) are not labelled
OCCLUSION_MIN_M = 0.3  # a point is hidden when it lies more than max(this, ...
OCCLUSION_FRACTION = 0.02  # ... this share of its depth) behind the rendered depth


def occluded(depth_image: np.ndarray, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Points (pixels uv, camera depth) hidden behind the rendered depth: more than
    max(OCCLUSION_MIN_M, OCCLUSION_FRACTION * depth) behind the farthest of the 2x2 pixel
    centres around them. Far away a ground point lies between two rows metres apart in depth,
    and the farther row is the one it must not be behind; at an occluder's edge this leaves the
    label at most one pixel into it (where the edge lies within the pixel is not known)."""
    h, w = depth_image.shape
    u0 = np.clip(np.floor(uv[:, 0]).astype(np.intp), 0, w - 1)
    v0 = np.clip(np.floor(uv[:, 1]).astype(np.intp), 0, h - 1)
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    rendered = np.maximum(np.maximum(depth_image[v0, u0], depth_image[v0, u1]),
                          np.maximum(depth_image[v1, u0], depth_image[v1, u1]))
    return depth > rendered + np.maximum(OCCLUSION_MIN_M, OCCLUSION_FRACTION * depth)


def project_lines(lines: list[np.ndarray], ids: list[int], sensor_to_odom: np.ndarray,
                  calib: CameraCalibration, depth_image: np.ndarray, stamp_ns: int
                  ) -> tuple[ImageLabels, list[np.ndarray]]:
    """Odom-frame GT polylines -> the visible pieces in the image (near end first), and the
    same pieces in 3D (odom frame): the GT of exactly what the labels show."""
    to_cloud = np.linalg.inv(sensor_to_odom)
    lanes, pieces_3d = [], []
    for line, line_id in zip(lines, ids):
        pts = resample_polyline(line, LABEL_STEP_M)
        if pts.shape[0] < 2:
            continue
        uv, depth, inside = calib.project(pts @ to_cloud[:3, :3].T + to_cloud[:3, 3])
        keep = inside & (depth <= LABEL_RANGE_M)
        keep[keep] = ~occluded(depth_image, uv[keep], depth[keep])
        for a, b in runs(keep):
            if b - a < 2:
                continue
            order = slice(None) if depth[a] <= depth[b - 1] else slice(None, None, -1)
            lanes.append(LaneLabel2D(int(line_id), uv[a:b][order].copy()))
            pieces_3d.append(pts[a:b][order].copy())
    labels = ImageLabels(int(stamp_ns), calib.camera_frame, (calib.width, calib.height), lanes)
    return labels, pieces_3d


def sim_image_labels(sim: Simulator, calib: CameraCalibration, image: CameraImage
                     ) -> tuple[ImageLabels, list[np.ndarray]]:
    """Labels of a SimCamera image of the simulator's scene (calib: SimCamera.calibration()),
    and their 3D GT pieces (odom frame)."""
    pose = sim.true_poses[image.index]
    lines, ids = crop_to_disc(sim.scene.lane_lines, image.camera_to_odom[:2, 3],
                              LABEL_RANGE_M + 10.0)
    return project_lines(lines, ids, pose, calib, image.depth, image.stamp_ns)


COLOURS = ((230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180),
           (70, 240, 240), (240, 50, 230), (210, 245, 60))


def draw_labels(rgb: np.ndarray, labels: ImageLabels, width: int = 2) -> Image.Image:
    """The image with each label piece drawn as a polyline (colour by line id) and a dot at its
    near end."""
    picture = Image.fromarray(rgb)
    pen = ImageDraw.Draw(picture)
    for lane in labels.lanes:
        colour = COLOURS[lane.id % len(COLOURS)]
        pen.line([tuple(p) for p in lane.uv.tolist()], fill=colour, width=width)
        u, v = lane.uv[0]
        pen.ellipse((u - 3, v - 3, u + 3, v + 3), fill=colour)
    return picture


def main(argv: list[str] | None = None) -> int:
    """`python -m fhld_ros.sim.labels2d_gt PNG --seed S --sweep K`: one simulated image with
    its 2D labels drawn over it (docs/sim_camera.png)."""
    parser = argparse.ArgumentParser(prog='python -m fhld_ros.sim.labels2d_gt')
    parser.add_argument('png')
    parser.add_argument('--seed', type=int, default=3)
    parser.add_argument('--sweep', type=int, default=5)
    args = parser.parse_args(argv)
    sim = Simulator(args.seed, sweeps=args.sweep + 1)
    camera = SimCamera(sim)
    image = camera.render(args.sweep)
    labels, _ = sim_image_labels(sim, camera.calibration(), image)
    draw_labels(image.rgb, labels).save(args.png, optimize=True)
    print(f'{args.png}: seed {args.seed} sweep {args.sweep}, {len(labels.lanes)} label pieces')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
