"""The ``saliency`` stage variants (paper Sec. III-B): BEV -> per-pixel saliency in [0, 1].

``selfreformer`` (the paper's SelfReformer*, retrained on BEV ground images), ``u2net``, ``u2netp``
and ``ldf`` are learned; ``classical`` is a learning-free detector of painted markings. Learned
variants load safetensors weights (the package's by default), run in PyTorch or onnxruntime at
``input_size`` and resize the probability back to the BEV; torch is imported only when one is built.
"""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from sgf_pipeline import RunContext, Stage, StageParams
from sgf_pipeline.cache import file_hash
from sgf_pipeline.types import Bev, SaliencyMap
from sgf_plugins.saliency.classical import marking_saliency
from sgf_plugins.saliency.models import ARCHITECTURES


class ClassicalParams(StageParams):
    """Parameters of the learning-free painted-marking detector."""

    kernel_m: float = Field(0.8, gt=0.0, description="top-hat disc diameter (m): markings narrower than this are kept")
    polarity: Literal["bright", "dark", "both"] = Field("bright", description="paint brighter or darker than ground")
    min_contrast: float = Field(12.0, ge=0.0, description="lowest top-hat response (grey levels) called paint")
    k_sigma: float = Field(4.0, ge=0.0, description="adaptive threshold: robust standard deviations of the top-hat")
    min_area_m2: float = Field(0.01, ge=0.0, description="components smaller than this (m^2) are dropped")
    smooth_px: float = Field(1.0, ge=0.0, description="Gaussian smoothing before the top-hat (pixels)")


class ClassicalSaliency(Stage):
    """Learning-free painted-marking saliency: white top-hat and an adaptive threshold on the BEV."""

    kind = "saliency"
    name = "classical"
    output = "saliency"
    Params = ClassicalParams

    def process(self, bev: Bev) -> SaliencyMap:
        """Saliency of the BEV's painted markings, zero where the camera does not see the ground."""
        p: ClassicalParams = self.params  # type: ignore[assignment]
        prob = marking_saliency(
            bev.image,
            bev.valid,
            bev.grid.resolution,
            kernel_m=p.kernel_m,
            polarity=p.polarity,
            min_contrast=p.min_contrast,
            k_sigma=p.k_sigma,
            min_area_m2=p.min_area_m2,
            smooth_px=p.smooth_px,
        )
        return SaliencyMap(prob, bev)


class GroundTruthParams(StageParams):
    """Parameters of the ground-truth saliency (an ablation's upper bound)."""

    object_masks: bool = Field(True, description="close each marking's strokes into one object, as the training masks")


class GroundTruthSaliency(Stage):
    """Perfect saliency from the dataset's marking instances: the upper bound of an ablation (needs ground truth).

    It answers what the rest of the pipeline (detector, descriptor, association, loop, back-end) achieves
    when saliency is solved; it is never a default. Datasets without marking instances are refused.
    """

    kind = "saliency"
    name = "ground_truth"
    output = "saliency"
    Params = GroundTruthParams

    def process(self, bev: Bev) -> SaliencyMap:
        """1 on every marking pixel the camera sees, 0 elsewhere."""
        if bev.instance_ids is None:
            from sgf_pipeline.errors import DataError

            raise DataError(
                "saliency=ground_truth needs marking instances in the BEV (a synthetic campus dataset, or a "
                "folder dataset with masks); choose a detector such as saliency=selfreformer"
            )
        paint = (bev.instance_ids > 0) & bev.valid
        if self.params.object_masks:  # type: ignore[attr-defined]
            from sgf_plugins.saliency.synthetic_data import ObjectMaskParams, object_mask

            paint = object_mask(bev.image, paint, bev.valid, ObjectMaskParams())
        return SaliencyMap(paint.astype(np.float32), bev)


class LearnedParams(StageParams):
    """Parameters shared by the learned saliency networks."""

    weights: str | None = Field(None, description="safetensors weights file; null = the weights shipped in the package")
    runtime: Literal["torch", "onnx"] = Field(
        "onnx", description="inference engine: onnxruntime (exported once and cached; faster on CPU) or PyTorch"
    )
    input_size: int = Field(128, ge=32, description="network input side (px): the BEV is resized to it and back")
    threads: int | None = Field(
        None, ge=1, description="intra-op threads of the runtime; null = torch's (run.torch_threads sets it)"
    )
    onnx_path: str | None = Field(
        None, description="ONNX file to use or create for runtime=onnx; null = a cache file keyed by the weights"
    )
    mask_invalid: bool = Field(True, description="zero the saliency where the camera does not see the ground")


class LearnedSaliency(Stage):
    """Base of the learned variants: load the network once, then one forward pass per BEV.

    A missing or mismatched weights file raises :class:`~sgf_pipeline.errors.DataError` naming the
    file, the expected architecture and how to get fitting weights.
    """

    kind = "saliency"
    output = "saliency"
    Params: ClassVar[type[StageParams]] = LearnedParams
    #: The variant's architecture parameters (fields of its Params).
    arch_fields: ClassVar[tuple[str, ...]] = ()
    #: The input size must be a multiple of this.
    size_multiple: ClassVar[int] = 1

    def __init__(self, params: StageParams) -> None:
        super().__init__(params)
        from sgf_plugins.saliency.inference import SaliencyPredictor
        from sgf_plugins.saliency.weights import resolve_weights_path

        p: LearnedParams = params  # type: ignore[assignment]
        if p.input_size % self.size_multiple:
            raise ValueError(
                f"saliency={self.name}: input_size {p.input_size} must be a multiple of {self.size_multiple}"
            )
        self.weights_path = resolve_weights_path(self.name, p.weights)
        self.predictor = SaliencyPredictor(
            self.name, self.architecture(), self.weights_path, p.input_size, p.runtime, p.threads, p.onnx_path
        )

    def cache_identity(self) -> dict[str, str]:
        """The weights' content hash: new weights make new saliency maps."""
        return {"weights": file_hash(Path(self.weights_path))}

    def architecture(self) -> dict[str, object]:
        """The architecture parameters of this instance."""
        return {k: getattr(self.params, k) for k in self.arch_fields}

    def begin(self, context: RunContext) -> None:
        """Match onnxruntime's threads to torch's, which the runner has set from ``run.torch_threads``."""
        super().begin(context)
        self.predictor.follow_torch_threads()

    def process(self, bev: Bev) -> SaliencyMap:
        """Saliency probability of the BEV at its own resolution."""
        prob = self.predictor.predict(bev.image)
        if self.params.mask_invalid:  # type: ignore[attr-defined]
            prob = prob * np.asarray(bev.valid, dtype=np.float32)
        return SaliencyMap(prob.astype(np.float32), bev)


class SelfReformerParams(LearnedParams):
    """SelfReformer* (the paper's model): PVT-v2 encoder, global context, CRM refinement, fusers."""

    input_size: int = Field(
        256,
        ge=32,
        description="network input side (px): 256 = the default BEV at its 2 cm/px; the BEV is resized to it and back",
    )

    size: Literal["t", "b0", "b1", "b2"] = Field(
        "t", description="PVT-v2 encoder size: b0, b1, b2 as published, t = reduced for CPU (16-32-64-64 wide)"
    )
    global_dim: int = Field(64, ge=16, multiple_of=16, description="width of the global-context branch (paper: 256)")
    level_depth: int = Field(1, ge=1, description="transformer blocks per encoder level (paper: 2)")
    crm_depth: int = Field(1, ge=1, description="transformer blocks in each context refinement module (paper: 4)")
    mlp_ratio: int = Field(3, ge=1, description="MLP expansion of the decoder's transformer blocks (paper: 3)")


class SelfReformerSaliency(LearnedSaliency):
    """SelfReformer* salient ground features (Yun and Lin 2022, retrained on BEV ground images)."""

    name = "selfreformer"
    Params = SelfReformerParams
    arch_fields = ARCHITECTURES["selfreformer"]
    size_multiple = 32


class U2NetParams(LearnedParams):
    """U^2-Net: nested residual U-blocks with six side outputs and a fused output."""

    width: float = Field(0.25, gt=0.0, le=1.0, description="channel multiplier of every RSU stage (paper: 1)")


class U2NetSaliency(LearnedSaliency):
    """U^2-Net salient object detection (Qin et al. 2020), reduced widths for CPU."""

    name = "u2net"
    Params = U2NetParams
    arch_fields = ARCHITECTURES["u2net"]


class U2NetPParams(LearnedParams):
    """U^2-Net-P: the small U^2-Net (16 inner, 64 outer channels in every stage)."""

    width: float = Field(1.0, gt=0.0, le=1.0, description="channel multiplier of every RSU stage (paper: 1)")


class U2NetPSaliency(LearnedSaliency):
    """U^2-Net-P salient object detection (the 1.1 M-parameter U^2-Net)."""

    name = "u2netp"
    Params = U2NetPParams
    arch_fields = ARCHITECTURES["u2netp"]


class LdfParams(LearnedParams):
    """LDF: label decoupling into body and detail, two interacting branches on a ResNet encoder."""

    resnet_depth: Literal[18, 34, 50] = Field(18, description="ResNet encoder depth (paper: 50)")
    resnet_width: int = Field(32, ge=8, description="ResNet base width (paper: 64)")
    branch_width: int = Field(32, ge=8, description="width of the body and detail branches (paper: 64)")


class LdfSaliency(LearnedSaliency):
    """Label Decoupling Framework salient object detection (Wei et al. 2020), reduced for CPU."""

    name = "ldf"
    Params = LdfParams
    arch_fields = ARCHITECTURES["ldf"]


LEARNED_VARIANTS: tuple[type[LearnedSaliency], ...] = (SelfReformerSaliency, U2NetSaliency, U2NetPSaliency, LdfSaliency)
VARIANTS: tuple[type[Stage], ...] = (*LEARNED_VARIANTS, ClassicalSaliency, GroundTruthSaliency)


def default_architecture(model: str) -> dict[str, object]:
    """The architecture parameters of a learned variant at their defaults (those of its config file)."""
    cls = {c.name: c for c in LEARNED_VARIANTS}[model]
    return {k: cls.Params.model_fields[k].default for k in cls.arch_fields}
