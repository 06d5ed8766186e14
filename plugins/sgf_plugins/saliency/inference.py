"""Running a trained saliency network on images: in PyTorch, or exported to ONNX and run by onnxruntime."""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import cv2
import numpy as np

from sgf_pipeline.cache import caches_root, file_hash
from sgf_pipeline.errors import DataError
from sgf_plugins.saliency.preprocess import as_rgb, normalize_image

if TYPE_CHECKING:
    import torch
    from torch import nn

ONNX_OPSET = 17


def onnx_cache_dir() -> Path:
    """Where exported ONNX models are kept: ``onnx/`` of sgf-pipeline's caches (``~/.cache/sgf_pipeline``)."""
    return caches_root() / "onnx"


def load_network(model: str, arch: Mapping[str, Any], weights: str | Path, input_size: int | None = None) -> nn.Module:
    """The network of ``model`` with weights loaded, in eval mode.

    Weights that record the input size they were trained at warn when ``input_size`` differs: the
    network then sees the ground at another scale (metres per input pixel) than it learned.
    """
    from sgf_plugins.saliency.models import build_model
    from sgf_plugins.saliency.weights import load_weights, trained_input_size

    net = build_model(model, arch)
    trained = trained_input_size(load_weights(net, weights, model, arch))
    if input_size is not None and trained is not None and trained != input_size:
        warnings.warn(
            f"saliency={model}: {weights} was trained at input size {trained}, run at {input_size}; "
            f"set saliency.input_size={trained} unless the BEV's resolution differs as much",
            stacklevel=2,
        )
    return net.eval()


def probability_module(net: nn.Module) -> nn.Module:
    """Wrap a network so that it maps a normalised image batch to the final saliency probability."""
    from torch import nn

    class SaliencyProbability(nn.Module):
        """sigmoid(final logit) of a saliency network, ``(B, 1, H, W)``."""

        def __init__(self, inner: nn.Module) -> None:
            super().__init__()
            self.inner = inner

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            """Probability at input resolution."""
            import torch

            return torch.sigmoid(self.inner.final(self.inner(x)))  # type: ignore[operator]

    return SaliencyProbability(net).eval()


def export_onnx(net: nn.Module, path: str | Path, input_size: int) -> Path:
    """Export a network (probability output) to ONNX at a fixed input size, atomically."""
    import torch

    from sgf_pipeline.io import atomic_path

    module = probability_module(net)
    dummy = torch.zeros(1, 3, input_size, input_size)
    target = Path(path)
    with atomic_path(target) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            (dummy,),
            str(tmp),
            input_names=["image"],
            output_names=["probability"],
            opset_version=ONNX_OPSET,
            dynamo=False,
        )
    module.eval()
    return target


def onnx_cache_path(model: str, arch: Mapping[str, Any], weights: Path, input_size: int) -> Path:
    """A cache file name that changes with the weights' bytes, the architecture, the input size and torch."""
    import torch

    key = json.dumps(
        {"arch": dict(arch), "weights": file_hash(weights), "size": input_size, "torch": torch.__version__},
        sort_keys=True,
    )
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    return onnx_cache_dir() / f"{model}-{input_size}-{digest}.onnx"


class SaliencyPredictor:
    """A trained network that maps an RGB image of any size to a saliency probability of the same size."""

    def __init__(
        self,
        model: str,
        arch: Mapping[str, Any],
        weights: str | Path,
        input_size: int,
        runtime: Literal["torch", "onnx"] = "torch",
        threads: int | None = None,
        onnx_path: str | Path | None = None,
    ) -> None:
        self.model = model
        self.input_size = input_size
        self.runtime = runtime
        self.threads = threads
        self.weights = Path(weights)
        net = load_network(model, arch, weights, input_size)
        self._torch: nn.Module | None = None
        self._session: Any = None
        self.onnx_path: Path | None = None
        if runtime == "torch":
            import torch

            if threads:
                torch.set_num_threads(threads)  # process-wide, like the runner's run.torch_threads
            self._torch = probability_module(net)
        elif runtime == "onnx":
            path = Path(onnx_path) if onnx_path else onnx_cache_path(model, arch, self.weights, input_size)
            if not path.is_file():
                export_onnx(net, path, input_size)
            self.onnx_path = path
            self._session = _ort_session(path, self.session_threads())
        else:
            raise ValueError(f"unknown runtime {runtime!r}; use torch or onnx")

    def session_threads(self) -> int:
        """The intra-op threads of onnxruntime: ``threads``, else torch's (which ``run.torch_threads`` sets)."""
        import torch

        return self.threads or torch.get_num_threads()

    def follow_torch_threads(self) -> None:
        """Rebuild the onnxruntime session when torch's thread count changed since it was made (threads=null)."""
        if self._session is not None and self.onnx_path is not None and self._session_threads != self.session_threads():
            self._session = _ort_session(self.onnx_path, self.session_threads())

    @property
    def _session_threads(self) -> int:
        return int(self._session.get_session_options().intra_op_num_threads)

    def network_input(self, rgb: np.ndarray) -> np.ndarray:
        """The normalised network input ``(1, 3, S, S)`` of an RGB image."""
        return normalize_image(rgb, self.input_size)[None]

    def predict_network(self, x: np.ndarray) -> np.ndarray:
        """Probabilities ``(B, S, S)`` of normalised inputs ``(B, 3, S, S)`` at the network's resolution."""
        if self._session is not None:
            return np.asarray(self._session.run(None, {"image": x.astype(np.float32)})[0])[:, 0]
        import torch

        assert self._torch is not None
        with torch.inference_mode():
            return self._torch(torch.from_numpy(x)).numpy()[:, 0]

    def predict(self, rgb: np.ndarray) -> np.ndarray:
        """Saliency probability ``(H, W)`` float32 in [0, 1] of an RGB image ``(H, W, 3)`` (or a grey one)."""
        rgb = as_rgb(rgb)
        h, w = rgb.shape[:2]
        prob = self.predict_network(self.network_input(rgb))[0]
        if prob.shape != (h, w):
            prob = cv2.resize(prob, (w, h), interpolation=cv2.INTER_LINEAR)
        return np.clip(prob, 0.0, 1.0).astype(np.float32)


def _ort_session(path: Path, threads: int) -> Any:
    """An onnxruntime CPU session with ``threads`` intra-op threads."""
    try:
        import onnxruntime as ort
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise DataError(f"runtime=onnx needs onnxruntime: {exc}") from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:
        raise DataError(f"onnxruntime cannot load {path}: {exc}; delete it to export it again") from None
