"""TracedFeatures: FhldDetector.features as a frozen TorchScript graph, for serving.

In the node the model shares its Python process with the ROS executor. Eager PyTorch takes the
GIL back between every op, and each time it can wait for the executor's Python loop; a traced
graph runs all ops in C++ without the GIL. Freezing also folds batch norms into convolutions.
Outputs equal the eager ones to float rounding (test_model.py). The graph is traced for one
raster shape on one device; another shape falls back to eager.
"""
from __future__ import annotations

import warnings

import torch
from torch import Tensor, nn

from fhld_ros.model.detector import FhldDetector


class _Features(nn.Module):
    def __init__(self, model: FhldDetector) -> None:
        super().__init__()
        self.model = model

    def forward(self, raster: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return self.model.features(raster)


class TracedFeatures:
    """Callable raster (1, C, H, W) -> model.features(raster), traced on first use."""

    def __init__(self, model: FhldDetector) -> None:
        self.model = model.eval()
        self.graph: torch.jit.ScriptModule | None = None
        self.shape: tuple[int, ...] | None = None

    def __call__(self, raster: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        with torch.no_grad():
            if self.graph is None:
                self.model.check_input(raster)
                with warnings.catch_warnings():  # shape checks become constants: intended
                    warnings.simplefilter('ignore', torch.jit.TracerWarning)
                    traced = torch.jit.trace(_Features(self.model).eval(), raster,
                                             check_trace=False)
                self.graph, self.shape = torch.jit.freeze(traced), tuple(raster.shape)
            if tuple(raster.shape) != self.shape:
                return self.model.features(raster)
            return self.graph(raster)
