"""The stage contract: what a plugin implements to add a variant of a pipeline stage."""

from __future__ import annotations

import inspect
import typing
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Optional, TypeVar

from pydantic import BaseModel, ConfigDict

from sgf_pipeline.context import RunContext
from sgf_pipeline.types import Frame, GroupAssignment, LoopConstraints, SgfDescriptor

T = TypeVar("T")


class _PreviousFrame:
    """Marker: the input takes the value produced on the previous frame (a feedback edge)."""

    def __repr__(self) -> str:
        return "PREVIOUS_FRAME"


PREVIOUS_FRAME = _PreviousFrame()

#: An input annotated ``Previous[T]`` receives the ``T`` produced on the previous frame (or
#: ``None`` on the first). Such edges close feedback loops (the back-end's estimate feeding the
#: association of the next frame) without making the stage graph cyclic.
Previous = Annotated[Optional[T], PREVIOUS_FRAME]  # noqa: UP045  (Annotated needs the Optional form)


class StageParams(BaseModel):
    """Base of every stage's ``Params``: unknown keys are refused, values are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


@dataclass(frozen=True)
class SettledGroup:
    """An SGF group as the association leaves it at the end of a run."""

    group_id: int
    members: tuple[SgfDescriptor, ...]
    symmetric: bool


@dataclass(frozen=True)
class Settlement:
    """What stages hand each other at the end of a run, passed along the stage graph in DAG order.

    The runner starts from an empty ``Settlement()`` and gives it to every stage's ``settle`` in DAG
    order, then to every stage's ``conclude``; each stage returns it with what it decided replaced
    (``dataclasses.replace``). The fields, and who fills them in the default pipeline:

    - ``groups`` and ``group_of``: the association's final SGF groups (after its split and merge at
      the end; ``None`` without an association) and each SGF's ``(frame_index, track_id)`` -> its
      final group;
    - ``final_loops``: loops the loop stage closed at the end (its final pass);
    - ``assignments``: every group assignment the loop stage received, for the SGF map.
    """

    groups: tuple[SettledGroup, ...] | None = None
    group_of: Mapping[tuple[int, int], int] = field(default_factory=dict)
    final_loops: LoopConstraints = field(default_factory=lambda: LoopConstraints(()))
    assignments: tuple[GroupAssignment, ...] = ()


class Stage(ABC):
    """One variant of a pipeline stage.

    Subclasses set ``kind`` (the config group), ``name`` (the variant), ``output`` (the name of
    the value they produce) and ``Params``; ``process`` takes its inputs as keyword parameters
    named like the outputs of other stages, and its annotations are the types checked on edges.

    The end of a run has two passes over the stages in DAG order. First every stage's ``settle``;
    then, stage by stage, ``conclude`` and ``finalize``. ``settle`` and ``conclude`` take the
    :class:`Settlement` the stages before handed on and return it, with their own decisions in it;
    ``finalize`` finishes the stage's results (metrics, trajectories, files). A stage that hands
    nothing on overrides ``finalize`` alone: the defaults of ``settle`` and ``conclude`` pass the
    settlement through.
    """

    kind: ClassVar[str]
    name: ClassVar[str]
    output: ClassVar[str]
    Params: ClassVar[type[StageParams]] = StageParams
    #: Whether the runner may keep this stage's outputs in the stage cache (:mod:`sgf_pipeline.cache`)
    #: when they depend only on the dataset and the stages before it; ``False`` for a stage whose
    #: outputs depend on anything else (the clock, a random source without a seed parameter).
    cacheable: ClassVar[bool] = True
    #: Whether the stage cache keeps this stage's outputs; ``False`` for outputs that cost more to
    #: store than to compute (an image filter's image): then only its changes to the run context are
    #: kept, and it runs whenever a stage after it misses.
    cache_outputs: ClassVar[bool] = True

    def __init__(self, params: StageParams) -> None:
        self.params = params

    def cache_identity(self) -> dict[str, str]:
        """What the outputs depend on besides the variant, its parameters and its code (a weights file's hash).

        Part of the stage cache's key; parameters naming files are identified by their content already.
        """
        return {}

    @property
    def read_ahead(self) -> float:
        """Metres of path after a frame that must be driven before this stage processes the frame.

        When a stage of a pipeline asks for some, ``Pipeline.frames`` reads the dataset that far
        ahead and fills ``Frame.path_ahead``: the whole pipeline then runs that far behind the camera.
        """
        return 0.0

    def begin(self, context: RunContext) -> None:  # noqa: B027  (optional hook, empty by design)
        """Reset per-sequence state before the first frame."""

    @abstractmethod
    def process(self, *args: Any, **kwargs: Any) -> Any:
        """Compute this stage's output for one frame."""

    def settle(self, context: RunContext, settlement: Settlement) -> Settlement:
        """Make the end-of-run decisions that every stage's ``conclude`` builds on; the settlement handed on.

        Called on every stage in DAG order before any ``conclude``: a later stage can settle what
        an earlier one concludes with (the loop stage takes back the loops outside the largest
        consistent set, the back-end re-solves without them, and the association regroups by that
        estimate in its ``conclude``).
        """
        return settlement

    def conclude(self, context: RunContext, settlement: Settlement) -> Settlement:
        """Make the last end-of-run decisions, on what every stage settled; the settlement handed on.

        Called in DAG order, each stage's right before its ``finalize`` (the association's final
        groups, then the loop stage's final pass over them, whose loops the back-end's ``finalize``
        adds to its final optimisation).
        """
        return settlement

    def finalize(self, context: RunContext) -> None:  # noqa: B027  (optional hook, empty by design)
        """Finish the sequence: final optimisation, metrics, trajectories, files."""

    def partial(self, context: RunContext, settlement: Settlement) -> Settlement:
        """Keep what the run has so far when it stops early (SIGINT, SIGTERM, a failure).

        Instead of the end-of-run passes, the runner calls ``partial`` on every stage in DAG order
        before it records the stopped run, handing on the settlement as ``settle`` does (the loop
        stage's group assignments so far, for the back-end's SGF map): a stage publishes its results
        so far into ``context`` (the back-end its trajectory, written as
        ``trajectory_<name>.partial.tum``) or writes them as ``*.partial.*`` files (the SGF map).
        Best effort: the stop may have come in the middle of the stage's own ``process``.
        """
        return settlement


class Dataset(ABC):
    """The source of a pipeline: a sequence of frames in time order (config group ``dataset``)."""

    kind: ClassVar[str] = "dataset"
    name: ClassVar[str]
    output: ClassVar[str] = "frame"
    Params: ClassVar[type[StageParams]] = StageParams

    def __init__(self, params: StageParams) -> None:
        self.params = params

    @abstractmethod
    def frames(self) -> Iterator[Frame]:
        """Yield the sequence's frames in time order."""

    def __len__(self) -> int:
        """Number of frames, or 0 when unknown in advance."""
        return 0

    def cache_identity(self) -> dict[str, str]:
        """What the frames depend on besides the variant, its parameters, its code and the files they name.

        Part of the stage cache's key (:mod:`sgf_pipeline.cache`).
        """
        return {}

    def begin(self, context: RunContext) -> None:  # noqa: B027  (optional hook, empty by design)
        """Fill what the dataset knows into the run context (calibration, ground truth)."""

    def finalize(self, context: RunContext) -> None:  # noqa: B027  (optional hook, empty by design)
        """Release resources at the end of the sequence."""


StageClass = type[Stage] | type[Dataset]


@dataclass(frozen=True)
class InputSpec:
    """One input of a stage: its parameter name, expected type and edge kind."""

    parameter: str
    annotation: Any
    types: tuple[type, ...]
    optional: bool
    previous: bool

    def describe(self) -> str:
        """Human-readable type of this input."""
        names = " | ".join(t.__name__ for t in self.types)
        return f"Previous[{names}]" if self.previous else names


@dataclass(frozen=True)
class StageSignature:
    """The inputs and output type of a stage class, read from its ``process`` annotations."""

    inputs: tuple[InputSpec, ...]
    output_types: tuple[type, ...]
    output_optional: bool


def _split_optional(annotation: Any) -> tuple[tuple[type, ...], bool]:
    """Return the concrete classes of an annotation and whether it admits ``None``."""
    origin = typing.get_origin(annotation)
    if origin is typing.Union or (origin is not None and str(origin) == "<class 'types.UnionType'>"):
        args = typing.get_args(annotation)
        optional = type(None) in args
        types_ = tuple(a for a in args if a is not type(None))
    else:
        types_, optional = (annotation,), False
    resolved: list[type] = []
    for t in types_:
        base = typing.get_origin(t) or t
        if not isinstance(base, type):
            raise TypeError(f"annotation {t!r} is not a class")
        resolved.append(base)
    return tuple(resolved), optional


def signature_of(cls: StageClass) -> StageSignature:
    """Read the typed inputs and output of a stage class."""
    if issubclass(cls, Dataset):
        return StageSignature(inputs=(), output_types=(Frame,), output_optional=False)
    try:
        hints = typing.get_type_hints(cls.process, include_extras=True)
    except NameError as exc:
        raise TypeError(
            f"{cls.__qualname__}.process has an annotation that cannot be resolved ({exc}); "
            "import the types it names at module level"
        ) from None
    params = list(inspect.signature(cls.process).parameters.values())[1:]
    inputs: list[InputSpec] = []
    for p in params:
        if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            raise TypeError(f"{cls.__qualname__}.process must name its inputs; *args/**kwargs are not allowed")
        if p.name not in hints:
            raise TypeError(f"{cls.__qualname__}.process: input {p.name!r} has no type annotation")
        annotation = hints[p.name]
        previous = False
        if typing.get_origin(annotation) is Annotated:
            base, *extras = typing.get_args(annotation)
            previous = any(e is PREVIOUS_FRAME for e in extras)
            annotation = base
        types_, optional = _split_optional(annotation)
        inputs.append(InputSpec(p.name, hints[p.name], types_, optional or previous, previous))
    if "return" not in hints:
        raise TypeError(f"{cls.__qualname__}.process has no return annotation (the output type)")
    out_types, out_optional = _split_optional(hints["return"])
    return StageSignature(tuple(inputs), out_types, out_optional)
