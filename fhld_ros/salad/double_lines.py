"""Double lines decoded as two: a lane whose near pixels show two stripes side by side is
split into one lane per stripe.

The two stripes of a double centre line lie 0.2-0.35 m apart (centre to centre): at 10 m a
cell of the network's map spans both, so the segmentation marks one line and the decoding
gives one lane between them, which the metric pairs with one stripe and counts the other
missed (docs/salad.md, "Double lines"). The image still shows them apart near the camera (at
10 m one virtual-camera pixel is 2.5 cm). So across each decoded lane's near points (NEAR_M),
brightness is sampled every ACROSS_STEP_M; a point shows two stripes where its two brightest
peaks lie SEPARATION_M apart, each standing out from the road beside the lane by
MIN_CONTRAST, with the pixels between them darker than half way down to the road. A lane
with MIN_SHARE of its tested points so is replaced by two lanes, offset by the median centre
and half the median separation of those points, each with its score. Dashed stripes (a solid
and a dashed line, passing allowed on one side) show both only along their dashes, hence a
share, not a majority.
"""
from __future__ import annotations

import numpy as np

from fhld_ros.salad.paint_evidence import across_brightness, across_road, near_points
from fhld_ros.salad.virtual_camera import VirtualCamera

NEAR_M = (4.0, 15.0)
ACROSS_STEP_M = 0.025
ACROSS_M = np.arange(-12, 13) * ACROSS_STEP_M  # +-0.30 m: the stripes and the lane's error
SEPARATION_M = (0.15, 0.40)
ROAD_BESIDE_M = np.array([0.5, 0.65, 0.8])
MIN_CONTRAST = 1.3
DIP = 0.5  # between the stripes, at most half way from the road up to the dimmer stripe
MIN_SHARE = 0.2  # solid beside dashed: the dashes cover a quarter of the length or more
MIN_POINTS = 6
CENTROID_SAMPLES = 4  # a stripe's place: the brightness within 10 cm of its brightest sample


def split_double_lines(lanes: list[np.ndarray], scores: np.ndarray, image: np.ndarray,
                       camera: VirtualCamera) -> tuple[list[np.ndarray], np.ndarray]:
    """The lanes ((N, 3) optical frame, near to far) and their scores with every double line
    split in two, seen in the virtual camera's image (height, width, 3) uint8."""
    scores = np.asarray(scores)
    if not lanes:
        return lanes, scores
    points, across, lane = near_points(lanes, NEAR_M)
    if not len(points):
        return lanes, scores
    image = np.asarray(image)
    profile = across_brightness(points, across, ACROSS_M, image, camera).astype(np.float64)
    beside = across_brightness(points, across, np.concatenate([-ROAD_BESIDE_M, ROAD_BESIDE_M]),
                               image, camera).astype(np.float64)
    centre, separation = _two_stripes(profile, beside)
    in_view = profile.min(axis=1) >= 0
    out_lanes, out_scores = [], []
    for i, (points_i, score) in enumerate(zip(lanes, scores)):
        tested = (lane == i) & in_view
        double = tested & np.isfinite(separation)
        if tested.sum() < MIN_POINTS or double.sum() < MIN_SHARE * tested.sum():
            out_lanes.append(points_i)
            out_scores.append(score)
            continue
        shift, half = float(np.median(centre[double])), 0.5 * float(np.median(separation[double]))
        side = across_road(points_i)
        out_lanes += [points_i + (shift - half) * side, points_i + (shift + half) * side]
        out_scores += [score, score]
    return out_lanes, np.asarray(out_scores, dtype=scores.dtype)


def _two_stripes(profile: np.ndarray, beside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point (rows of profile, brightness across the lane at ACROSS_M): the offset of the
    midpoint between its two stripes and their separation (m), NaN where it shows no two."""
    road = np.median(np.where(beside >= 0, beside, np.nan), axis=1)
    index = np.arange(profile.shape[1])
    first = profile.argmax(axis=1)
    apart = np.abs(index[None] - first[:, None]) * ACROSS_STEP_M
    candidates = (apart >= SEPARATION_M[0]) & (apart <= SEPARATION_M[1])
    second = np.where(candidates, profile, -np.inf).argmax(axis=1)
    rows = np.arange(len(profile))
    peak = profile[rows, second]
    left = profile[rows, np.maximum(second - 1, 0)]
    right = profile[rows, np.minimum(second + 1, len(index) - 1)]
    low, high = np.minimum(first, second), np.maximum(first, second)
    between = (index[None] > low[:, None]) & (index[None] < high[:, None])
    dip = np.where(between, profile, np.inf).min(axis=1)
    with np.errstate(invalid='ignore'):
        two = (candidates[rows, second] & (peak >= left) & (peak >= right)
               & (peak >= MIN_CONTRAST * road) & (dip <= road + DIP * (peak - road)))
    at_first, at_second = (_centroid(profile, road, peak, other)
                           for peak, other in ((first, second), (second, first)))
    centre = np.where(two, 0.5 * (at_first + at_second), np.nan)
    separation = np.where(two, np.abs(at_first - at_second), np.nan)
    return centre, separation


def _centroid(profile: np.ndarray, road: np.ndarray, peak: np.ndarray, other: np.ndarray
              ) -> np.ndarray:
    """Per row, the offset (m) of the brightness above the road within CENTROID_SAMPLES of the
    peak's sample and nearer it than the other peak's: a stripe a few samples wide has a flat
    top, and argmax takes its first sample."""
    index = peak[:, None] + np.arange(-CENTROID_SAMPLES, CENTROID_SAMPLES + 1)
    mine = np.abs(index - peak[:, None]) < np.abs(index - other[:, None])
    index = np.clip(index, 0, profile.shape[1] - 1)
    weight = np.clip(np.take_along_axis(profile, index, axis=1) - road[:, None], 0.0, None)
    weight = np.where(mine & np.isfinite(weight), weight, 0.0)
    total = weight.sum(axis=1)
    return np.where(total > 0, (weight * ACROSS_M[index]).sum(axis=1) /
                    np.maximum(total, 1e-9), ACROSS_M[peak])
