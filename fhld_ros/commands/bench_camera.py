"""`fhld bench camera` and `fhld bench camera_live`: SALAD, the camera detector, on 960x540
images of a simulated drive (salad/sim_source.py, the fixed camera of seed BENCH_SEED).

camera: medians (ms) over REPEATS runs of each stage as camera_lane_detector runs it, with the
node's default model_threads and model_runtime, and flip_average as
FHLD_BENCH_CAMERA_FLIP_AVERAGE says (default 0, one pass, the node's default; 1: the mirror too):
camera_warp_ms (resampling to the virtual camera; camera_warp_distorted_ms: the same with a
lens's distortion removed, the PJLab camera's), camera_model_ms (the network as served, on
the image and its mirror with flip_average; camera_model_eager_ms: the same network in eager
torch), camera_jpeg_decode_ms (a CompressedImage JPEG of the image, quality 90, to pixels: what
image_transport:=compressed adds; camera_bayer_decode_ms: a bayer_rggb8 mosaic of it,
demosaiced), camera_decode_ms (maps -> 3D lanes, on the maps of the image's own ground-truth
lanes, so it costs what a real detection of them costs whatever the weights;
camera_decode_network_ms
on the network's own maps, whose stray cells make more points), and camera_e2e_ms_p50 /
_p95: image message in -> the three /lanes messages out through CameraPipeline (decode,
checks, SALAD, frames, ids, outline, serialisation).

camera_live: the node as its own process over DDS (loopback) with its default parameters
(flip_average as above), fed one camera_info, then rgb8 images (1.5 MB) and camera_info at 10
Hz on the wall clock for FHLD_BENCH_CAMERA_SECONDS (default 20): latency = /lanes arrival -
image publish, an image whose stamp never comes back on /lanes is dropped, and the node's own
counters (overtaken, lost by DDS) and stage medians from its /diagnostics. On each transport
`dds` names, in a bench process of its own as e2e's (bench_e2e.transport_child): 'project'
(config/fastdds_loopback.xml) and 'default' (Fast DDS's 512 kB segment: an image travels in
fragments); keys camera_live_project_*, camera_live_default_*.

Both use the shipped fhld_ros/checkpoints/salad.pt; where it is absent an untrained model of
SaladConfig's defaults (row statistics of the bench image) stands in, and camera_weights says
so: the timings of warp and network depend on the view's width (640 px, the defaults' and
the shipped weights'), not on the weights, but such a model finds no lanes, so its
camera_e2e_ms decodes none (camera_decode_ms has the cost).
"""
from __future__ import annotations

import dataclasses
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from fhld_ros.commands.bench_stages import time_median
from fhld_ros.lane_output import lane_messages
from fhld_ros.ros.env import loopback_dds_env
from fhld_ros.salad.camera_pipeline import CameraPipeline, load_camera_detector
from fhld_ros.salad.checkpoint import DEFAULT_SALAD_CHECKPOINT, save_salad
from fhld_ros.salad.config import SaladConfig
from fhld_ros.salad.decode import decode
from fhld_ros.salad.model import SaladNet
from fhld_ros.salad.parameters import CameraParams
from fhld_ros.salad.sample import CameraLaneSample
from fhld_ros.salad.sim_source import simulated_samples
from fhld_ros.salad.targets import lane_targets, row_statistics
from msg_adapters.camera import (
    camera_info_msg,
    compressed_image_msg,
    image_to_msg,
    msg_to_image,
)
from msg_adapters.family import rosbags_family

BENCH_SEED = 4_000_123  # a held-out SALAD seed (sim_source.salad_seeds('test') starts at 4e6)
SIZE = (960, 540)
REPEATS = 30
SECONDS = float(os.environ.get('FHLD_BENCH_CAMERA_SECONDS', '20'))
FLIP_AVERAGE = os.environ.get('FHLD_BENCH_CAMERA_FLIP_AVERAGE', '0') != '0'
RATE_HZ = 10.0
LENS = np.array([-0.108, 0.139, -0.0038, -0.0048, 0.0])  # the PJLab camera's plumb_bob
START_NS = 1_700_000_000_000_000_000
NODE_START_TIMEOUT_SEC = 90.0
# the node's counters (/diagnostics) reported as camera_live_node_<name>
NODE_COUNTERS = ('images_overtaken', 'images_skipped', 'bad_images', 'images_lost_in_dds')


def _sample() -> CameraLaneSample:
    return next(simulated_samples(BENCH_SEED, 1, SIZE, randomise=False))


def _weights(sample: CameraLaneSample, folder: Path) -> tuple[Path, str]:
    """(checkpoint, what it is): the shipped one, else an untrained model of the defaults."""
    if DEFAULT_SALAD_CHECKPOINT.is_file():
        return DEFAULT_SALAD_CHECKPOINT, 'shipped'
    cfg = SaladConfig()
    targets = lane_targets(sample.lanes, cfg.camera)
    shift, scale = row_statistics(targets.depth[None], targets.depth_mask[None])
    cfg = dataclasses.replace(cfg, row_shift=tuple(map(float, shift)),
                              row_scale=tuple(map(float, scale)))
    torch.manual_seed(0)
    path = folder / 'salad_untrained.pt'
    save_salad(path, SaladNet(cfg), 'fhld bench camera: untrained stand-in')
    return path, f'untrained ({DEFAULT_SALAD_CHECKPOINT.name} absent)'


def _decode_ms(sample: CameraLaneSample, cfg: SaladConfig) -> float:
    """decode() on the maps of the image's own lanes (as a model that found them gives)."""
    targets = lane_targets(sample.lanes, cfg.camera)
    spatial = np.concatenate([targets.offsets, cfg.depth_residual(targets.depth)[None]])
    prob = targets.seg * 0.9
    return time_median(lambda: decode(prob, spatial, cfg), repeats=REPEATS, warmup=2)


def bench_camera() -> dict[str, float | str]:
    """`fhld bench camera`: see the module doc."""
    sample = _sample()
    threads = torch.get_num_threads()
    try:
        return _bench_camera(sample)
    finally:
        torch.set_num_threads(threads)  # the detector set the node's: later sections keep theirs


def _bench_camera(sample: CameraLaneSample) -> dict[str, float | str]:
    with tempfile.TemporaryDirectory() as folder:
        checkpoint, weights = _weights(sample, Path(folder))
        params = CameraParams(checkpoint=str(checkpoint), flip_average=FLIP_AVERAGE)
        detector = load_camera_detector(params)
    cfg = detector.cfg
    image, k = sample.image, sample.intrinsics
    warp_ms = time_median(lambda: cfg.camera.warp(image, k), repeats=REPEATS)
    distorted_ms = time_median(lambda: cfg.camera.warp(image, k, LENS), repeats=REPEATS)
    x = detector.batch(cfg.camera.warp(image, k))  # as served: with its mirror, if flip_average

    def eager() -> None:
        with torch.inference_mode():
            detector.model(x)
    model_ms = time_median(lambda: detector.network(x), repeats=REPEATS, warmup=3)
    maps = detector.maps(image, k)
    eager_ms = time_median(eager, repeats=REPEATS, warmup=3)
    family = rosbags_family()
    jpeg = compressed_image_msg(family, family.header(0, 'camera'), image, 'jpeg')
    jpeg_ms = time_median(lambda: msg_to_image(jpeg), repeats=REPEATS)
    bayer = image_to_msg(family, family.header(0, 'camera'), image, 'bayer_rggb8')
    bayer_ms = time_median(lambda: msg_to_image(bayer), repeats=REPEATS)
    pipeline = CameraPipeline(params, detector)
    pipeline.receive_camera_info(camera_info_msg(family, family.header(0, 'camera'), *SIZE, k))
    msg = image_to_msg(family, family.header(0, 'camera'), image)
    e2e, lanes = [], []
    for n in range(REPEATS + 3):
        msg.header.stamp = family.stamp(START_NS + n * 100_000_000)
        start = time.perf_counter()
        pipeline.receive_image(msg)
        out = pipeline.detect()
        lane_messages(out)
        e2e.append((time.perf_counter() - start) * 1e3)
        lanes.append(len(out.lanes))
    p50, p95 = np.percentile(e2e[3:], [50, 95])
    return {'camera_weights': weights, 'camera_image': f'{SIZE[0]}x{SIZE[1]}',
            'camera_torch_threads': float(torch.get_num_threads()),
            'camera_model_runtime': type(detector.network).__name__,
            'camera_flip_average': float(FLIP_AVERAGE),
            'camera_warp_ms': warp_ms, 'camera_warp_distorted_ms': distorted_ms,
            'camera_model_ms': model_ms,
            'camera_model_eager_ms': eager_ms, 'camera_jpeg_decode_ms': jpeg_ms,
            'camera_bayer_decode_ms': bayer_ms,
            'camera_decode_ms': _decode_ms(sample, cfg),
            'camera_decode_network_ms': time_median(lambda: decode(*maps, cfg), repeats=REPEATS),
            'camera_decode_lanes': float(len(sample.lanes)),
            'camera_e2e_ms_p50': float(p50), 'camera_e2e_ms_p95': float(p95),
            'camera_e2e_lanes': float(statistics.median(lanes))}


class _LiveClient:
    """Publishes images + camera_info, times /lanes arrivals, keeps the node's /diagnostics."""

    def __init__(self, context, sample: CameraLaneSample) -> None:
        from fhld_ros.commands.bench_e2e import LanesClient  # rclpy: only for camera_live
        self.ros = LanesClient(context, 'fhld_bench_camera')
        self.family = family = self.ros.family
        self.image = self.ros.node.create_publisher(family.cls('sensor_msgs/msg/Image'),
                                                    'camera/image_raw', self.ros.reliable)
        self.info = self.ros.node.create_publisher(family.cls('sensor_msgs/msg/CameraInfo'),
                                                   'camera/camera_info', self.ros.reliable)
        self.image_msg = image_to_msg(family, family.header(0, 'camera'), sample.image)
        self.info_msg = camera_info_msg(family, family.header(0, 'camera'), *SIZE,
                                        sample.intrinsics)
        self.ros.start()

    def publish(self, count: int) -> dict[int, float]:
        """`count` images at RATE_HZ on the wall clock; stamp -> publish time of each."""
        published: dict[int, float] = {}
        # a camera_info ahead of the stream: across topics DDS keeps no order, and an image
        # before the first camera_info is dropped (measured here: the first image, once)
        self.info_msg.header.stamp = self.family.stamp(START_NS - int(1e9 / RATE_HZ))
        self.info.publish(self.info_msg)
        time.sleep(0.5)
        t0 = time.monotonic()
        for k in range(count):
            stamp = START_NS + k * int(1e9 / RATE_HZ)
            for msg in (self.info_msg, self.image_msg):
                msg.header.stamp = self.family.stamp(stamp)
            time.sleep(max(0.0, t0 + k / RATE_HZ - time.monotonic()))
            self.info.publish(self.info_msg)
            published[stamp] = time.monotonic()
            self.image.publish(self.image_msg)
        return published

def bench_camera_live(seconds: float = SECONDS,
                      dds: str | tuple[str, ...] = ('project', 'default')
                      ) -> dict[str, float | str]:
    """`fhld bench camera_live`: see the module doc."""
    from fhld_ros.commands.bench_e2e import transport_child, transports  # rclpy: only here
    results: dict[str, float | str] = {}
    for name in transports(dds):
        summary = transport_child('fhld_ros.commands.bench_camera', seconds, name)
        results.update({f'camera_live_{name}_{k.removeprefix("camera_live_")}': v
                        for k, v in summary.items()})
    return results


def _measure_live(seconds: float, dds: str) -> dict[str, float | str]:
    """One transport in this process: the node as a child process, images, /lanes timed."""
    import rclpy
    os.environ.update(loopback_dds_env(dds=dds))  # before rclpy.init and the node read it
    sample = _sample()
    with tempfile.TemporaryDirectory() as folder:
        checkpoint, weights = _weights(sample, Path(folder))
        node = subprocess.Popen([sys.executable, '-m', 'fhld_ros.ros.camera_lane_detector',
                                 '--ros-args', '-p', f'checkpoint:={checkpoint}',
                                 '-p', f'flip_average:={str(FLIP_AVERAGE).lower()}'],
                                env=dict(os.environ), stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        context = rclpy.Context()
        rclpy.init(context=context)
        client = _LiveClient(context, sample)
        try:
            client.ros.wait_for(node, (client.image, client.info), 'camera_lane_detector',
                               NODE_START_TIMEOUT_SEC)
            published = client.publish(int(seconds * RATE_HZ))
            time.sleep(2.0)  # the last detections and a /diagnostics
        finally:
            node.terminate()
            node.wait(timeout=30)
            client.ros.close()
            context.try_shutdown()
    latencies = np.array([(t - published[s]) * 1e3 for s, t in client.ros.arrivals
                          if s in published])
    if latencies.size < 3:
        raise RuntimeError(f'only {latencies.size} /lanes messages arrived')
    return {'camera_live_weights': weights, 'camera_live_seconds': float(seconds),
            'camera_live_images_published': float(len(published)),
            'camera_live_images_dropped': float(len(published) - len(
                {s for s, _ in client.ros.arrivals} & set(published))),
            'camera_live_latency_ms_p50': float(np.percentile(latencies, 50)),
            'camera_live_latency_ms_p95': float(np.percentile(latencies, 95)),
            **{f'camera_live_node_{k}': float(v) for k, v in client.ros.diag.items()
               if k.startswith(('stage_', 'latency_ms_'))},
            **{f'camera_live_node_{k}': float(client.ros.diag.get(k, 0.0))
               for k in NODE_COUNTERS}}


if __name__ == '__main__':
    from fhld_ros.commands.bench_e2e import transport_main
    transport_main('camera_live', _measure_live, SECONDS)
