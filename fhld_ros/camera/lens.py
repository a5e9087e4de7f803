"""Lens distortion as sensor_msgs/CameraInfo names it, with OpenCV's equations: `plumb_bob`
(k1 k2 p1 p2 k3), `rational_polynomial` (k1 k2 p1 p2 k3 k4 k5 k6: the radial term a ratio of
two polynomials, as wide lenses calibrate) and `equidistant` (k1 k2 k3 k4: OpenCV's fisheye
model, the distorted radius a polynomial in the ray's angle off the axis).

A Lens maps normalised pinhole coordinates (z = 1) to where the lens puts them and back; it is
hashable, so per-camera maps built from it can be cached.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PLUMB_BOB, RATIONAL, EQUIDISTANT = 'plumb_bob', 'rational_polynomial', 'equidistant'
# the coefficients each takes in d: fewest (the rest zero), all
MODELS = {PLUMB_BOB: (4, 5), RATIONAL: (5, 8), EQUIDISTANT: (4, 4)}
UNDISTORT_STEPS = 10
# a fisheye's border lies near or beyond 90 degrees off the axis, where a pinhole's
# normalised coordinates run to infinity: rays are kept this far inside it
MAX_ANGLE_RAD = np.radians(89.0)


@dataclass(frozen=True)
class Lens:
    model: str
    coefficients: tuple[float, ...]  # all the model's, in camera_info's d order

    @classmethod
    def from_camera_info(cls, model: str, d: np.ndarray | list[float]) -> Lens | None:
        """camera_info's distortion_model and d -> a Lens, None for none (d all zero); a
        plumb_bob d may give four (k3 = 0), a rational_polynomial d five (k4..k6 = 0).
        ValueError naming the problem."""
        d = np.asarray(d, dtype=np.float64).ravel()
        if not np.all(np.isfinite(d)):
            raise ValueError(f'distortion d {d.tolist()} is not finite')
        if not np.any(d):
            return None
        model = model or PLUMB_BOB  # some drivers leave the model empty
        if model not in MODELS:
            raise ValueError(f'distortion_model {model!r} is not supported (supported: '
                             f'{", ".join(MODELS)})')
        fewest, n = MODELS[model]
        if d.size < fewest or np.any(d[n:]):
            count = f'{n}' if fewest == n else f'{fewest} to {n}'
            raise ValueError(f'distortion_model {model} takes {count} coefficients in d, got '
                             f'{d.size}')
        return cls(model, tuple(float(c) for c in np.append(d, np.zeros(n))[:n]))

    @classmethod
    def plumb_bob(cls, d: np.ndarray) -> Lens | None:
        """A (4,) or (5,) plumb_bob D, as the calibrations and simulated samples hold it."""
        return cls.from_camera_info(PLUMB_BOB, d)

    def __str__(self) -> str:
        return f'{self.model} {", ".join(f"{c:.4g}" for c in self.coefficients)}'

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised pinhole coordinates -> where the lens puts them (normalised)."""
        if self.model == EQUIDISTANT:
            r = np.hypot(x, y)
            theta = np.arctan(r)
            scale = np.where(r > 1e-12, self._fisheye_radius(theta) / np.maximum(r, 1e-12), 1.0)
            return x * scale, y * scale
        k1, k2, p1, p2, k3, k4, k5, k6 = self._polynomial()
        r2 = x * x + y * y
        radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)

    def undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inverse of distort(): by Newton's method on the fisheye's angle, by fixed-point
        iteration for the polynomial models (as OpenCV's undistortPoints)."""
        if self.model == EQUIDISTANT:
            rd = np.hypot(xd, yd)
            theta = np.minimum(rd, MAX_ANGLE_RAD)
            for _ in range(UNDISTORT_STEPS):
                slope = self._fisheye_slope(theta)
                theta = theta - (self._fisheye_radius(theta) - rd) / np.where(
                    np.abs(slope) > 1e-9, slope, 1e-9)
                theta = np.clip(theta, 0.0, MAX_ANGLE_RAD)
            scale = np.where(rd > 1e-12, np.tan(theta) / np.maximum(rd, 1e-12), 1.0)
            return xd * scale, yd * scale
        k1, k2, p1, p2, k3, k4, k5, k6 = self._polynomial()
        x, y = xd, yd
        for _ in range(UNDISTORT_STEPS):
            r2 = x * x + y * y
            radial = (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) / \
                (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
            x = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / radial
            y = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / radial
        return x, y

    def unfolded(self, x: np.ndarray, y: np.ndarray, corner_r2: float) -> np.ndarray:
        """Where distort() is one-to-one: a polynomial folds back into the image far beyond the
        corners (squared normalised radius corner_r2, undistorted estimate); a fisheye's radius
        up to where it stops growing with the angle."""
        r2 = x * x + y * y
        if self.model != EQUIDISTANT:
            return r2 < 4.0 * corner_r2
        angles = np.linspace(0.0, MAX_ANGLE_RAD, 512)
        falling = np.flatnonzero(self._fisheye_slope(angles) <= 0)
        limit = angles[falling[0]] if len(falling) else MAX_ANGLE_RAD
        return np.arctan(np.sqrt(r2)) < limit

    def _polynomial(self) -> tuple[float, ...]:
        return (*self.coefficients, 0.0, 0.0, 0.0)[:8]

    def _fisheye_radius(self, theta: np.ndarray) -> np.ndarray:
        k1, k2, k3, k4 = self.coefficients
        t2 = theta * theta
        return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def _fisheye_slope(self, theta: np.ndarray) -> np.ndarray:
        k1, k2, k3, k4 = self.coefficients
        t2 = theta * theta
        return 1.0 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))


def as_lens(distortion: Lens | np.ndarray | None) -> Lens | None:
    """A Lens, a plumb_bob D array (k1 k2 p1 p2 [k3]) or None -> a Lens or None (none)."""
    if distortion is None or isinstance(distortion, Lens):
        return distortion
    return Lens.plumb_bob(distortion)
