"""Serving runtimes for FhldDetector.features (and SALAD's network): ONNX Runtime on CPU,
TorchScript elsewhere.

In the node the model shares its Python process with the ROS executor. Eager PyTorch takes the
GIL back between every op, and each time it can wait for the executor's Python loop; both
runtimes here run the whole graph in C++ without the GIL.

- OnnxGraph (CPU): the graph exported to ONNX in memory and run by ONNX Runtime (by default
  one thread per core). Its workers do not spin, so between detections they leave the cores to
  the ROS executor, where torch's OpenMP threads would compete with it. The timings of both
  runtimes are in docs/performance.md; how ONNX Runtime came to serve the model, in
  docs/history.md.
- TracedGraph (CUDA, or CPU without onnxruntime): a frozen TorchScript trace; freezing
  folds batch norms into convolutions.

Outputs equal the eager ones to float rounding (test_model.py, test_salad.py). Both are built
for one input shape on first use; another shape falls back to eager.
"""
from __future__ import annotations

import importlib.util
import io
import warnings
from collections.abc import Callable

import torch
from torch import Tensor, nn

from fhld_ros.model.detector import FhldDetector

Features = tuple[Tensor, Tensor, Tensor]


class _Features(nn.Module):
    def __init__(self, model: FhldDetector) -> None:
        super().__init__()
        self.model = model

    def forward(self, raster: Tensor) -> Features:
        return self.model.features(raster)


class ShapeBoundGraph:
    """Callable x -> module(x) (a tensor or a tuple of them) through a graph built for the first
    input's shape; `check` (optional) refuses a bad first input before the graph is built."""

    def __init__(self, module: nn.Module, check: Callable[[Tensor], None] | None = None
                 ) -> None:
        self.module = module.eval()
        self.check = check
        self.graph = None
        self.shape: tuple[int, ...] | None = None

    def __call__(self, x: Tensor) -> tuple[Tensor, ...]:
        with torch.no_grad():
            if self.graph is None:
                if self.check is not None:
                    self.check(x)
                with warnings.catch_warnings():  # shape checks become constants: intended
                    warnings.simplefilter('ignore')
                    self.graph = self._build(self.module, x)
                self.shape = tuple(x.shape)
            if tuple(x.shape) != self.shape:
                return tuple(self.module(x))
            return self._run(x)

    def _build(self, module: nn.Module, x: Tensor):
        raise NotImplementedError

    def _run(self, x: Tensor) -> tuple[Tensor, ...]:
        raise NotImplementedError


class TracedGraph(ShapeBoundGraph):
    """The module as a frozen TorchScript trace."""

    def _build(self, module: nn.Module, x: Tensor) -> torch.jit.ScriptModule:
        return torch.jit.freeze(torch.jit.trace(module, x, check_trace=False))

    def _run(self, x: Tensor) -> tuple[Tensor, ...]:
        return tuple(self.graph(x))


class OnnxGraph(ShapeBoundGraph):
    """The module exported to ONNX (in memory) and run by ONNX Runtime on the CPU."""

    def __init__(self, module: nn.Module, check: Callable[[Tensor], None] | None = None,
                 threads: int = 0) -> None:
        super().__init__(module, check)
        self.threads = threads

    def _build(self, module: nn.Module, x: Tensor):
        import onnxruntime

        model_bytes = io.BytesIO()
        torch.onnx.export(module, (x,), model_bytes, dynamo=False, opset_version=17,
                          input_names=['input'])
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = max(self.threads, 0)  # 0: one per physical core
        options.inter_op_num_threads = 1
        # Spinning workers would take the cores the ROS callbacks need between ops.
        options.add_session_config_entry('session.intra_op.allow_spinning', '0')
        options.log_severity_level = 3  # errors only
        return onnxruntime.InferenceSession(model_bytes.getvalue(), options,
                                            providers=['CPUExecutionProvider'])

    def _run(self, x: Tensor) -> tuple[Tensor, ...]:
        return tuple(torch.from_numpy(out) for out in self.graph.run(None, {'input': x.numpy()}))


class TracedFeatures(TracedGraph):
    """model.features as a frozen TorchScript trace."""

    def __init__(self, model: FhldDetector) -> None:
        super().__init__(_Features(model), model.check_input)


class OnnxFeatures(OnnxGraph):
    """model.features exported to ONNX and run by ONNX Runtime on the CPU."""

    def __init__(self, model: FhldDetector, threads: int = 0) -> None:
        super().__init__(_Features(model), model.check_input, threads)


def serving_graph(module: nn.Module, device: str = 'cpu', runtime: str = 'auto',
                  threads: int = 0, check: Callable[[Tensor], None] | None = None
                  ) -> ShapeBoundGraph:
    """How a served network runs: 'auto' is ONNX Runtime on the CPU when it is installed, else
    TorchScript; 'onnxruntime' (CPU only) or 'torchscript'. ValueError when 'onnxruntime' is
    asked for and not installed."""
    missing = _missing_onnx_packages()
    if runtime == 'onnxruntime' and missing:
        raise ValueError(f"model_runtime 'onnxruntime' needs the {missing} package(s)")
    if runtime == 'onnxruntime' or (runtime == 'auto' and device == 'cpu' and not missing):
        return OnnxGraph(module, check, threads)
    return TracedGraph(module, check)


def serving_features(model: FhldDetector, device: str = 'cpu', runtime: str = 'auto',
                     threads: int = 0) -> ShapeBoundGraph:
    """The features runner the node and `fhld replay` serve with (runtime checked by
    DetectorParams; serving_graph)."""
    return serving_graph(_Features(model), device, runtime, threads, model.check_input)


def _missing_onnx_packages() -> str:
    """'' when the exporter (onnx) and onnxruntime import, else the missing names."""
    return ' and '.join(name for name in ('onnx', 'onnxruntime')
                        if importlib.util.find_spec(name) is None)
