"""Errors a user can act on: each message says what is wrong and how to fix it."""

from __future__ import annotations


class SgfError(Exception):
    """Base of the errors raised by sgf-pipeline."""


class ConfigError(SgfError, ValueError):
    """The configuration cannot build a pipeline (raised before the first frame)."""


class PluginError(SgfError):
    """A plugin failed to load or registered something that breaks the stage contract."""


class PipelineGraphError(ConfigError):
    """The configured stages do not form a valid graph (missing producer, cycle, type mismatch)."""


class DataError(SgfError, ValueError):
    """Input data (a dataset, a weights file, a map) is missing or malformed."""


class StageError(SgfError):
    """A stage failed while processing a frame; names the stage and the frame."""

    def __init__(self, message: str, kind: str, name: str, frame_index: int | None) -> None:
        super().__init__(message)
        self.kind = kind
        self.name = name
        self.frame_index = frame_index


class CacheError(SgfError):
    """The stage cache cannot be used as configured, or an entry disagrees with the run."""


class ImageNotCachedError(CacheError):
    """A frame read from the stage cache has no image: every stage that reads images took its outputs from the cache."""
