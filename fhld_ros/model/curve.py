"""Global lane curves: cubic polynomials w.r.t. a reference axis (paper eq. 1-3, 5).

A curve is stored as 12 numbers (p_s, p_e, a, b), each 3D in normalised units (u, v, z):

    f(t) = (1 - t) p_s + t p_e + t (1 - t) (a + b t)

which is the paper's A t^3 + B t^2 + C t + D with A = -b, B = b - a, C = p_e - p_s + a,
D = p_s. f(0) = p_s and f(1) = p_e hold exactly (also in floating point: the shape term is
multiplied by t (1 - t) = 0), so the boundary conditions (3) are met by construction.

The reference axis lies in the ground plane. The ground-plane parts of a and b are kept
perpendicular to it, so the ground-plane position of f(t) projects on the axis exactly at t and
the curve is a cubic "w.r.t. its axis"; the height is a free cubic of t.
- AdaptiveAxisCurve: axis p_s -> p_e (the paper).
- FixedAxisCurve: axis = the window x (forward) axis, i.e. y(x), z(x) cubics (ablation).
A point's parameter t is its projection on the axis of the curve's (GT) terminals (eq. 5).
"""
from __future__ import annotations

import torch
from torch import Tensor

_EPS = 1e-6
T_RANGE = (-0.5, 1.5)  # projections are clamped: a degenerate fixed axis must stay finite


def split(params: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(..., 12) -> p_s, p_e, a, b, each (..., 3)."""
    return params[..., 0:3], params[..., 3:6], params[..., 6:9], params[..., 9:12]


class AxisCubicCurve:
    """Shared maths; subclasses choose the reference axis (a ground-plane vector)."""

    def axis(self, p_s: Tensor, p_e: Tensor) -> Tensor:
        """(..., 2) ground-plane axis whose length spans t in [0, 1]."""
        raise NotImplementedError

    def unit_axis(self, p_s: Tensor, p_e: Tensor) -> Tensor:
        axis = self.axis(p_s, p_e)
        return axis / axis.norm(dim=-1, keepdim=True).clamp_min(_EPS)

    def constrain(self, raw: Tensor) -> Tensor:
        """Remove the along-axis ground-plane part of a and b: (..., 12) -> (..., 12)."""
        p_s, p_e, a, b = split(raw)
        unit = self.unit_axis(p_s, p_e)

        def perpendicular(vec: Tensor) -> Tensor:
            along = (vec[..., :2] * unit).sum(-1, keepdim=True)
            return torch.cat([vec[..., :2] - along * unit, vec[..., 2:]], dim=-1)

        return torch.cat([p_s, p_e, perpendicular(a), perpendicular(b)], dim=-1)

    @staticmethod
    def evaluate(params: Tensor, t: Tensor) -> Tensor:
        """Points f(t): params (..., 12), t (..., T) -> (..., T, 3)."""
        p_s, p_e, a, b = (v.unsqueeze(-2) for v in split(params))
        t = t.unsqueeze(-1)
        return (1 - t) * p_s + t * p_e + t * (1 - t) * (a + b * t)

    @staticmethod
    def coefficients(params: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The paper's (A, B, C, D), each (..., 3)."""
        p_s, p_e, a, b = split(params)
        return -b, b - a, p_e - p_s + a, p_s

    def project(self, points: Tensor, p_s: Tensor, p_e: Tensor) -> Tensor:
        """Eq. (5): t of points (..., K, 3) on the axis of terminals p_s, p_e (..., 3)."""
        axis = self.axis(p_s, p_e).unsqueeze(-2)
        rel = points[..., :2] - p_s[..., :2].unsqueeze(-2)
        t = (rel * axis).sum(-1) / (axis * axis).sum(-1).clamp_min(_EPS * _EPS)
        return t.clamp(*T_RANGE)

    @classmethod
    def curvature_xy(cls, params: Tensor, t: Tensor) -> Tensor:
        """Ground-plane curvature |x'y'' - y'x''| / |v|^3 at t, in 1/normalised units."""
        big_a, big_b, big_c, _ = (v.unsqueeze(-2) for v in cls.coefficients(params))
        t = t.unsqueeze(-1)
        d1 = 3 * big_a * t * t + 2 * big_b * t + big_c
        d2 = 6 * big_a * t + 2 * big_b
        cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
        speed = d1[..., :2].norm(dim=-1).clamp_min(_EPS)
        return cross.abs() / speed ** 3


class AdaptiveAxisCurve(AxisCubicCurve):
    """Cubic w.r.t. the lane's own axis p_s -> p_e (FHLD)."""

    def axis(self, p_s: Tensor, p_e: Tensor) -> Tensor:
        return p_e[..., :2] - p_s[..., :2]


class FixedAxisCurve(AxisCubicCurve):
    """Cubic w.r.t. the window's forward axis: y and z as cubics of x (ablation)."""

    def axis(self, p_s: Tensor, p_e: Tensor) -> Tensor:
        dx = p_e[..., :1] - p_s[..., :1]
        return torch.cat([dx, torch.zeros_like(dx)], dim=-1)

    def unit_axis(self, p_s: Tensor, p_e: Tensor) -> Tensor:
        unit = torch.zeros_like(p_s[..., :2])
        unit[..., 0] = 1.0
        return unit


def make_curve(adaptive_axis: bool) -> AxisCubicCurve:
    return AdaptiveAxisCurve() if adaptive_axis else FixedAxisCurve()
