"""camera_lane_detector's parameters, declared once for the node, `fhld replay --detector salad`
and parameter files (a `camera_lane_detector: ros__parameters:` section).

Each field's metadata 'doc' is its ROS ParameterDescriptor text; ranges and choices sit beside
it and are checked by the project's one checker (dataclass_dict.field_problems). No rclpy here.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from fhld_ros.dataclass_dict import documented, field_problems
from fhld_ros.errors import ConfigError
from fhld_ros.parameters import load_params_yaml
from fhld_ros.salad.paint_evidence import MIN_CONTRAST

NODE_NAME = 'camera_lane_detector'
IDENTITY = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class CameraParams:
    """Every parameter of camera_lane_detector; field metadata 'doc' is the ROS descriptor."""

    image_topic: str = documented(
        'camera/image_raw', 'input sensor_msgs/Image topic (rgb8, bgr8, rgba8, bgra8, mono8, '
        'yuv422, yuv422_yuy2, or an 8-bit Bayer mosaic: bayer_rggb8, bayer_bggr8, bayer_gbrg8, '
        "bayer_grbg8); camera_info's lens distortion (plumb_bob, rational_polynomial, "
        'equidistant) is removed from it',
        length='[1, inf)')
    image_transport: str = documented(
        'raw', "'raw': sensor_msgs/Image on image_topic; 'compressed': "
        'sensor_msgs/CompressedImage (JPEG, PNG) on <image_topic>/compressed, as '
        "image_transport's compressed publisher sends it", choices=('raw', 'compressed'))
    camera_info_topic: str = documented(
        'camera/camera_info', 'input sensor_msgs/CameraInfo topic; its newest message gives '
        'the intrinsics of each image', length='[1, inf)')
    image_rectified: bool = documented(
        False, "the images are rectified already (image_proc's image_rect): their intrinsics "
        "are camera_info's P (its left 3x3), and the raw lens's distortion D is not removed "
        'again; false: image_raw, K and D')
    lanes_topic: str = documented(
        'lanes', 'output MarkerArray topic; ego lane Paths go to <lanes_topic>/ego_left|right',
        length='[1, inf)')
    checkpoint: str = documented(
        '', 'SALAD weights (.pt), or the name of shipped ones: empty = salad (cameras 1.2-2.0 m '
        'over the road), salad_wide_mount (1.2-3.0 m)')
    model_threads: int = documented(
        0, 'CPU threads for the model; 0 = auto: one per core with ONNX Runtime, 1 with '
        'TorchScript (whose OpenMP threads beside other work ran the model up to 40x slower)',
        range='[0, 1024]')
    model_runtime: str = documented(
        'auto', "how the network runs: 'auto' (ONNX Runtime when installed, else TorchScript), "
        "'onnxruntime' or 'torchscript'", choices=('auto', 'onnxruntime', 'torchscript'))
    flip_average: bool = documented(
        False, 'average the network maps of the image and its mirror image (one batch of two: '
        'more accurate depth, twice the network time, over 50 ms on a 2-core CPU); false = one '
        'pass')
    road_profile: bool = documented(
        True, "pull the lane depths half way to the one road depth per image row that they "
        "share (no mount needed; a road's cross slope is fitted too); false = the network's "
        'depths as they are')
    min_paint_contrast: float = documented(
        MIN_CONTRAST, "lanes whose pixels are not this many times as bright as the road on "
        'each side of them are dropped: no lanes along kerbs, barriers or sidewalk edges '
        '(0.0 = off)', range='[0, 100]')
    double_lines: bool = documented(
        True, 'split a lane whose near pixels show two stripes side by side (a double centre '
        'line) into one lane per stripe; false = one lane between them')
    rate_hz: float = documented(
        10.0, 'detection rate on image stamps: an image at least 0.9 / rate_hz newer than the '
        'last detected one is detected, the others are skipped', range='(0, 1000]')
    score_threshold: float = documented(
        0.5, 'minimum lane score to publish (the checkpoint decodes lanes from its own '
        'threshold up)', range='[0, 1]')
    output_frame: str = documented(
        '', "frame of the published lanes; '' = the image's frame (the camera's optical "
        'frame: x right, y down, z forward)')
    camera_to_output: tuple[float, ...] = documented(
        IDENTITY, "the camera's optical frame in output_frame, [x, y, z, roll, pitch, yaw] "
        '(metres, radians, ROS fixed-axis RPY; a /tf_static transform output_frame -> camera). '
        'A camera level at 1.5 m over base_link: [0, 0, 1.5, -1.5708, 0, -1.5708]', length=6)
    road_plane_m: float = documented(
        0.0, "lanes nearer than this (metres) take their depth from the road under the camera: "
        "output_frame's z = 0 plane (e.g. base_footprint) through camera_to_output, blending "
        "into the network's depth up to 1.5 x this; 0 = off, the network's depth throughout "
        '(no extrinsics needed); 20 scored best on simulated validation drives',
        range='[0, 1000]')
    road_plane_pitch: str = documented(
        'mount', "with road_plane_m, where the road's pitch comes from: 'mount' "
        "(camera_to_output's) or 'image' (each image's own, where its lanes' image lines "
        "meet, the height and roll still camera_to_output's: for a mount known only by its "
        'height, or a car that pitches as it brakes)', choices=('mount', 'image'))
    camera_height_m: float = documented(
        1.5, 'height of the camera over the road, used for the searched-area outline when the '
        "detected lanes do not span a plane (the outline lies on the plane they span)",
        range='[0.1, 100]')
    input_reliability: str = documented(
        'auto', "image subscription reliability: 'auto' (reliable, switching to best effort "
        "while a best-effort publisher exists), 'reliable' or 'best_effort'",
        choices=('auto', 'reliable', 'best_effort'))

    def __post_init__(self) -> None:
        """ConfigError naming every value out of its declared range (all of them, one line)."""
        problems = field_problems(self)
        if not problems and self.camera_to_output != IDENTITY and not self.output_frame:
            problems.append('camera_to_output needs output_frame: the frame it maps the '
                            'camera into')
        if not problems and self.road_plane_m > 0 and not self.camera_to_output[2] > 0:
            problems.append(f'road_plane_m {self.road_plane_m:g} needs camera_to_output with '
                            "the camera above output_frame's z = 0 plane (the road), got z "
                            f'{self.camera_to_output[2]:g}')
        if problems:
            raise ConfigError('; '.join(problems))


def load_camera_params_yaml(path: str | Path, node_name: str = NODE_NAME) -> CameraParams:
    """CameraParams from a ROS 2 parameter file: the node's section, else the `/**` one;
    use_sim_time is accepted and left to ROS (fhld_ros.parameters.load_params_yaml)."""
    return load_params_yaml(path, node_name, CameraParams)
