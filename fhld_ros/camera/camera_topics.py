"""The camera in a bag, as `fhld simulate --camera` and `fhld import --images` write it and
`fhld autolabel` reads it: /tf_static once (the camera's pose in the cloud frame), then per
image /camera/camera_info and /camera/image_raw (rgb8) at the image's stamp."""
from __future__ import annotations

from typing import Any

import numpy as np

from fhld_ros.camera.calibration import CameraCalibration
from msg_adapters.camera import camera_info_msg, image_to_msg, tf_static_msg

CAMERA_INFO, IMAGE, TF_STATIC = '/camera/camera_info', '/camera/image_raw', '/tf_static'


def write_camera(bag: Any, calib: CameraCalibration, cloud_frame: str, stamp_ns: int,
                 rgb: np.ndarray, first: bool) -> None:
    """One image and its camera info into a bagio.BagWriter; the first also gets /tf_static."""
    fam = bag.family
    if first:
        bag.write(TF_STATIC, 'tf2_msgs/msg/TFMessage', stamp_ns,
                  tf_static_msg(fam, stamp_ns, cloud_frame, calib.camera_frame,
                                calib.camera_in_cloud))
    header = fam.header(stamp_ns, calib.camera_frame)
    bag.write(CAMERA_INFO, 'sensor_msgs/msg/CameraInfo', stamp_ns,
              camera_info_msg(fam, header, calib.width, calib.height, calib.K, calib.D,
                              calib.distortion_model))
    bag.write(IMAGE, 'sensor_msgs/msg/Image', stamp_ns, image_to_msg(fam, header, rgb))
