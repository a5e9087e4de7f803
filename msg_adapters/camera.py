"""Camera messages: sensor_msgs/Image and CompressedImage <-> (H, W, 3) uint8,
sensor_msgs/CameraInfo <-> pinhole intrinsics, and tf2_msgs/TFMessage <-> 4x4 transforms (any
message family, rosbags or rclpy)."""
from __future__ import annotations

import array
import io
from typing import Any

import numpy as np
from PIL import Image

from msg_adapters.bayer import BAYER_PATTERNS, demosaic, mosaic
from msg_adapters.family import MessageFamily
from msg_adapters.odometry import rigid_matrix, rigid_message

# encodings msg_to_image reads: channels and whether they are stored blue first
_ENCODINGS = {'rgb8': (3, False), 'bgr8': (3, True), 'mono8': (1, False),
              'rgba8': (4, False), 'bgra8': (4, True)}
# 4:2:2 YUV (two pixels in four bytes, as USB and GigE cameras send it): the byte offsets of
# Y0, U, Y1, V. ROS's 'yuv422' is UYVY; 'yuv422_yuy2' is YUYV.
_YUV422 = {'yuv422': (1, 0, 3, 2), 'uyvy': (1, 0, 3, 2), 'yuv422_yuy2': (0, 1, 2, 3),
           'yuyv': (0, 1, 2, 3)}
# what image_transport's compressed plugin writes; 'compressedDepth' is depth, not an image
_COMPRESSED_FORMATS = ('JPEG', 'PNG', 'TIFF')
_COLOUR_MODES = ('1', 'L', 'LA', 'P', 'PA', 'RGB', 'RGBA', 'RGBX', 'CMYK', 'YCbCr')


def image_to_msg(family: MessageFamily, header: Any, rgb: np.ndarray,
                 encoding: str = 'rgb8') -> Any:
    """(H, W, 3) uint8 RGB -> sensor_msgs/Image, encoding rgb8, or the 8-bit Bayer mosaic a
    sensor of that pattern records (bayer_rggb8, ...: for tests and benchmarks)."""
    rgb = np.ascontiguousarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f'image must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}')
    if encoding not in ('rgb8', *BAYER_PATTERNS):
        raise ValueError(f'image_to_msg writes rgb8 or {", ".join(BAYER_PATTERNS)}, not '
                         f'{encoding!r}')
    pixels = rgb if encoding == 'rgb8' else mosaic(rgb, encoding)
    height, width = rgb.shape[:2]
    return family.new('sensor_msgs/msg/Image', header=header, height=height, width=width,
                      encoding=encoding, is_bigendian=0, step=pixels[0].size,
                      data=_data_field(family, pixels.reshape(-1)))


def _data_field(family: MessageFamily, flat: np.ndarray) -> Any:
    # rosbags wants a numpy array; rclpy's uint8[] setter takes array('B') without a copy per item
    return flat if family.name == 'rosbags' else array.array('B', flat.tobytes())


def msg_to_image(msg: Any) -> np.ndarray:
    """sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8, 4:2:2 YUV: yuv422 / uyvy,
    yuv422_yuy2 / yuyv, or an 8-bit Bayer mosaic: bayer_rggb8, bggr8, gbrg8, grbg8; rows may be
    padded) or sensor_msgs/CompressedImage (JPEG, PNG or TIFF,
    as image_transport's compressed plugin writes them) -> (H, W, 3) uint8 RGB. ValueError for
    another encoding or format, or data that do not hold the image."""
    if not hasattr(msg, 'encoding') and hasattr(msg, 'format'):
        return compressed_to_image(msg)
    encoding = str(msg.encoding).lower()
    if encoding not in _ENCODINGS and encoding not in _YUV422 and encoding not in BAYER_PATTERNS:
        raise ValueError(f'image encoding {msg.encoding!r} is not supported (use '
                         f'{", ".join([*_ENCODINGS, *_YUV422, *BAYER_PATTERNS])})')
    # 4:2:2 YUV: 2 bytes a pixel; a Bayer mosaic: 1
    channels, blue_first = _ENCODINGS.get(encoding, (1 if encoding in BAYER_PATTERNS else 2,
                                                     False))
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(_as_bytes(msg.data), dtype=np.uint8)
    if step < width * channels or data.size < step * height or (channels == 2 and width % 2):
        raise ValueError(f'image {width}x{height} {encoding}: step {step} and {data.size} '
                         f'data bytes do not hold it')
    rows = data[:step * height].reshape(height, step)[:, :width * channels]
    if encoding in _YUV422:
        return _yuv422_to_rgb(rows.reshape(height, width // 2, 4), _YUV422[encoding])
    if encoding in BAYER_PATTERNS:
        return demosaic(rows, encoding)
    pixels = rows.reshape(height, width, channels)
    if channels == 1:
        return np.repeat(pixels, 3, axis=2)
    rgb = pixels[..., 2::-1] if blue_first else pixels[..., :3]
    return np.ascontiguousarray(rgb)


def _yuv422_to_rgb(pairs: np.ndarray, offsets: tuple[int, int, int, int]) -> np.ndarray:
    """(H, W / 2, 4) byte quads of two pixels -> (H, W, 3) RGB: BT.601 video range (Y 16-235,
    U and V 16-240), the usual camera YUV, each pixel pair sharing its U and V."""
    y0, u, y1, v = (pairs[..., i].astype(np.float32) for i in offsets)
    luma = (np.stack([y0, y1], axis=-1) - 16.0) * (255.0 / 219.0)  # (H, W / 2, 2)
    cb, cr = ((c - 128.0)[..., None] * (255.0 / 224.0) for c in (u, v))
    rgb = np.stack([luma + 1.402 * cr, luma - 0.344136 * cb - 0.714136 * cr,
                    luma + 1.772 * cb], axis=-1)  # (H, W / 2, 2, 3)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8).reshape(pairs.shape[0], -1, 3)


def compressed_to_image(msg: Any) -> np.ndarray:
    """sensor_msgs/CompressedImage -> (H, W, 3) uint8 RGB (grey images repeated into three
    channels). ValueError naming the format for data that are not a JPEG, PNG or TIFF image of
    8-bit channels, or do not decode."""
    fmt = str(msg.format)
    if 'compressedDepth' in fmt:
        raise ValueError(f'compressed image format {fmt!r} is a depth image, not a camera '
                         'image')
    try:
        with Image.open(io.BytesIO(_as_bytes(msg.data)), formats=_COMPRESSED_FORMATS) as image:
            if image.mode not in _COLOUR_MODES:
                raise ValueError(f'its pixels are {image.mode!r}, not 8-bit channels')
            return np.asarray(image.convert('RGB'))
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise ValueError(f'compressed image (format {fmt!r}, {len(msg.data)} bytes) does not '
                         f'decode as {", ".join(_COMPRESSED_FORMATS)}: {exc}') from None


def compressed_image_msg(family: MessageFamily, header: Any, rgb: np.ndarray,
                         fmt: str = 'jpeg', quality: int = 90) -> Any:
    """(H, W, 3) uint8 RGB -> sensor_msgs/CompressedImage as image_transport's compressed
    plugin writes it (format 'rgb8; jpeg compressed bgr8' or '... png ...')."""
    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb)).save(buffer, format=fmt.upper(),
                                                   quality=quality)
    flat = np.frombuffer(buffer.getvalue(), dtype=np.uint8)
    return family.new('sensor_msgs/msg/CompressedImage', header=header,
                      format=f'rgb8; {fmt} compressed bgr8', data=_data_field(family, flat))


def _as_bytes(data: Any) -> Any:
    if isinstance(data, np.ndarray):
        return data.reshape(-1).view(np.uint8)
    if isinstance(data, (bytes, bytearray, memoryview, array.array)):
        return data
    return bytes(data)  # a plain list of ints (some decoders)


def camera_info_msg(family: MessageFamily, header: Any, width: int, height: int,
                    K: np.ndarray, D: np.ndarray | None = None, model: str = 'plumb_bob'
                    ) -> Any:
    """sensor_msgs/CameraInfo of a camera: its lens `model`'s d (plumb_bob: [k1, k2, p1, p2,
    k3]), k row-major, p = [K | 0], r = identity (a monocular camera)."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    d = np.zeros(5) if D is None else np.asarray(D, dtype=np.float64).ravel()
    p = np.concatenate([K, np.zeros((3, 1))], axis=1)
    return family.new('sensor_msgs/msg/CameraInfo', header=header, height=int(height),
                      width=int(width), distortion_model=model,
                      d=_float_field(family, d), k=_float_field(family, K.ravel()),
                      r=_float_field(family, np.eye(3).ravel()),
                      p=_float_field(family, p.ravel()))


def _float_field(family: MessageFamily, values: np.ndarray) -> Any:
    return values.astype(np.float64) if family.name == 'rosbags' else \
        [float(v) for v in values]


def camera_info_values(msg: Any, rectified: bool = False
                       ) -> tuple[int, int, np.ndarray, str, np.ndarray, str]:
    """sensor_msgs/CameraInfo -> (width, height, K (3, 3), distortion_model, d (as given,
    e.g. (5,) or empty), frame_id) of the images it comes with: a binned or region-of-interest
    camera's (binning_x/y, roi; camera_info describes the full sensor) has its image size and
    K made those of its images. ValueError for a roi outside the sensor. For rectified images
    (image_proc's image_rect) the intrinsics are P's left 3x3 and d is empty, whatever lens
    the raw image came through."""
    if rectified:
        K, d = np.asarray(list(msg.p), dtype=np.float64).reshape(3, 4)[:, :3].copy(), np.zeros(0)
    else:
        K = np.asarray(list(msg.k), dtype=np.float64).reshape(3, 3)
        d = np.asarray(list(msg.d), dtype=np.float64)
    width, height, K = _binned(msg, K)
    return width, height, K, str(msg.distortion_model), d, str(msg.header.frame_id)


def _binned(msg: Any, K: np.ndarray) -> tuple[int, int, np.ndarray]:
    """The image size and K of the images a sensor's camera_info comes with: its roi cut out,
    then binning pixels combined (a binned pixel's centre is the mean of its sensor pixels',
    pixel (0, 0)'s centre at u = v = 0)."""
    width, height = int(msg.width), int(msg.height)
    bx, by = max(1, int(msg.binning_x)), max(1, int(msg.binning_y))
    roi = msg.roi
    x0, y0, w, h = int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height)
    if w == 0 or h == 0:  # the whole sensor (ROS: a roi of zeros)
        x0, y0, w, h = 0, 0, width, height
    elif x0 + w > width or y0 + h > height:
        raise ValueError(f'camera_info roi {w}x{h} at ({x0}, {y0}) lies outside the '
                         f'{width}x{height} sensor')
    if (bx, by, x0, y0, w, h) == (1, 1, 0, 0, width, height):
        return width, height, K
    S = np.array([[1.0 / bx, 0.0, -(x0 + (bx - 1) / 2) / bx],
                  [0.0, 1.0 / by, -(y0 + (by - 1) / 2) / by], [0.0, 0.0, 1.0]])
    return w // bx, h // by, S @ K


def transform_msg(family: MessageFamily, T: np.ndarray) -> Any:
    """4x4 -> geometry_msgs/Transform."""
    return rigid_message(family, T, 'geometry_msgs/msg/Transform', ('translation', 'rotation'),
                         'geometry_msgs/msg/Vector3')


def transform_to_matrix(transform: Any) -> np.ndarray:
    """geometry_msgs/Transform -> 4x4; ValueError for a non-finite translation or a rotation
    that is not a finite unit quaternion."""
    return rigid_matrix(transform.translation, transform.rotation,
                        ('transform translation', 'transform rotation'))


def tf_message(family: MessageFamily, stamp_ns: int,
               transforms: list[tuple[str, str, np.ndarray]]) -> Any:
    """tf2_msgs/TFMessage of (parent, child, T_parent_child) transforms, all at stamp_ns: each
    is the pose of child in parent (maps child-frame points into parent)."""
    return family.new('tf2_msgs/msg/TFMessage', transforms=[
        family.new('geometry_msgs/msg/TransformStamped', header=family.header(stamp_ns, parent),
                   child_frame_id=child, transform=transform_msg(family, T))
        for parent, child, T in transforms])


def tf_static_msg(family: MessageFamily, stamp_ns: int, parent: str, child: str,
                  T_parent_child: np.ndarray) -> Any:
    """A /tf_static message holding one transform: the pose of `child` in `parent`."""
    return tf_message(family, stamp_ns, [(parent, child, T_parent_child)])


def tf_transforms(msg: Any) -> list[tuple[str, str, np.ndarray]]:
    """tf2_msgs/TFMessage -> [(parent frame, child frame, T_parent_child 4x4)]."""
    return [(str(ts.header.frame_id), str(ts.child_frame_id), transform_to_matrix(ts.transform))
            for ts in msg.transforms]
