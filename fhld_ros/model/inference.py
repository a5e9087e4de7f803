"""Serving runtimes for FhldDetector.features: ONNX Runtime on CPU, TorchScript elsewhere.

In the node the model shares its Python process with the ROS executor. Eager PyTorch takes the
GIL back between every op, and each time it can wait for the executor's Python loop; both
runtimes here run the whole graph in C++ without the GIL.

- OnnxFeatures (CPU): the graph exported to ONNX in memory and run by ONNX Runtime (by default
  one thread per core). Its workers do not spin, so between detections they leave the cores to
  the ROS executor, where torch's OpenMP threads would compete with it. The timings of both
  runtimes are in docs/performance.md; how ONNX Runtime came to serve the model, in
  docs/history.md.
- TracedFeatures (CUDA, or CPU without onnxruntime): a frozen TorchScript trace; freezing
  folds batch norms into convolutions.

Outputs equal the eager ones to float rounding (test_model.py). Both are built for one raster
shape on first use; another shape falls back to eager.
"""
from __future__ import annotations

import importlib.util
import io
import warnings

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


class _ShapeBound:
    """Callable raster -> model.features(raster) through a graph built for the first shape."""

    def __init__(self, model: FhldDetector) -> None:
        self.model = model.eval()
        self.graph = None
        self.shape: tuple[int, ...] | None = None

    def __call__(self, raster: Tensor) -> Features:
        with torch.no_grad():
            if self.graph is None:
                self.model.check_input(raster)
                with warnings.catch_warnings():  # shape checks become constants: intended
                    warnings.simplefilter('ignore')
                    self.graph = self._build(_Features(self.model).eval(), raster)
                self.shape = tuple(raster.shape)
            if tuple(raster.shape) != self.shape:
                return self.model.features(raster)
            return self._run(raster)

    def _build(self, module: nn.Module, raster: Tensor):
        raise NotImplementedError

    def _run(self, raster: Tensor) -> Features:
        raise NotImplementedError


class TracedFeatures(_ShapeBound):
    """model.features as a frozen TorchScript trace."""

    def _build(self, module: nn.Module, raster: Tensor) -> torch.jit.ScriptModule:
        return torch.jit.freeze(torch.jit.trace(module, raster, check_trace=False))

    def _run(self, raster: Tensor) -> Features:
        return self.graph(raster)


class OnnxFeatures(_ShapeBound):
    """model.features exported to ONNX (in memory) and run by ONNX Runtime on the CPU."""

    def __init__(self, model: FhldDetector, threads: int = 0) -> None:
        super().__init__(model)
        self.threads = threads

    def _build(self, module: nn.Module, raster: Tensor):
        import onnxruntime

        model_bytes = io.BytesIO()
        torch.onnx.export(module, (raster,), model_bytes, dynamo=False, opset_version=17,
                          input_names=['raster'], output_names=['logits', 'curves', 'local'])
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = max(self.threads, 0)  # 0: one per physical core
        options.inter_op_num_threads = 1
        # Spinning workers would take the cores the ROS callbacks need between ops.
        options.add_session_config_entry('session.intra_op.allow_spinning', '0')
        options.log_severity_level = 3  # errors only
        return onnxruntime.InferenceSession(model_bytes.getvalue(), options,
                                            providers=['CPUExecutionProvider'])

    def _run(self, raster: Tensor) -> Features:
        outputs = self.graph.run(None, {'raster': raster.numpy()})
        return tuple(torch.from_numpy(out) for out in outputs)


def serving_features(model: FhldDetector, device: str = 'cpu', runtime: str = 'auto',
                     threads: int = 0) -> _ShapeBound:
    """The features runner the node and `fhld replay` serve with.

    runtime (checked by DetectorParams): 'auto' is ONNX Runtime on the CPU when it is
    installed, else TorchScript; 'onnxruntime' (CPU only) or 'torchscript'.
    """
    missing = _missing_onnx_packages()
    if runtime == 'onnxruntime' and missing:
        raise ValueError(f"model_runtime 'onnxruntime' needs the {missing} package(s)")
    if runtime == 'onnxruntime' or (runtime == 'auto' and device == 'cpu' and not missing):
        return OnnxFeatures(model, threads)
    return TracedFeatures(model)


def _missing_onnx_packages() -> str:
    """'' when the exporter (onnx) and onnxruntime import, else the missing names."""
    return ' and '.join(name for name in ('onnx', 'onnxruntime')
                        if importlib.util.find_spec(name) is None)
