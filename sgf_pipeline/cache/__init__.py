"""The stage cache: outputs of the stages that depend only on the dataset and the stages before them.

A stage is *cacheable* when none of its inputs is ``Previous[...]``, every stage it reads from is
cacheable (the dataset is), and it hands nothing on at the end of a run (no ``settle``, ``conclude``
or ``partial`` of its own). Its outputs over a run are then a pure function of the dataset and of
the stages before it, and are kept in an *entry* under a key that holds everything that can change
them (:mod:`~sgf_pipeline.cache.keys`): the dataset's variant, parameters and input files, the runner's
keyframe options, every upstream stage's variant and parameters, the code of those stages and of
the core, the stage's own identity (a weights file's hash), and the numeric libraries' versions.

An entry is a folder ``<kind>/<key>/`` of the cache's folder (``run.cache_dir``, by default
``~/.cache/sgf_pipeline/stages``): ``manifest.json`` (the key's components, sizes and
checksums: readable), ``records.jsonl`` (one JSON line per frame, :mod:`~sgf_pipeline.cache.codec`),
``arrays.zip`` (the arrays, zstd-compressed ``.npy`` members read without pickle) and ``effects.json`` (what the stage
put into the run context at ``begin`` and ``finalize``). An entry is written in a temporary folder
and renamed into place when its run has finished, so a reader sees whole entries only, and of two
jobs filling the same key one entry stays. A damaged entry is removed with a warning and
recomputed. The cache's size is bounded: the least recently used entries go first.

The dataset's keyframes (everything but their images) form an entry of kind ``dataset`` too: when
every cacheable stage hits, the dataset is not read, rendered or decoded at all. A stage whose
outputs cost more to store than to compute (``Stage.cache_outputs`` false: an image filter) keeps
only its changes to the run context; it is skipped when every stage reading its outputs hits, and
runs otherwise. When some stages hit, a keyframe's image is loaded only if a stage reads it.

Modules: :mod:`~sgf_pipeline.cache.keys` (what a key holds), :mod:`~sgf_pipeline.cache.codec`
(values as JSON and arrays), :mod:`~sgf_pipeline.cache.store` (the folder and its entries) and
:mod:`~sgf_pipeline.cache.plan` (a run's hits and misses).
"""

from sgf_pipeline.cache.keys import cacheable_nodes, code_fingerprint, file_hash
from sgf_pipeline.cache.plan import CachePlan
from sgf_pipeline.cache.store import (
    CACHE_ENV,
    STAGE_CACHE_ENV,
    EntryInfo,
    StageCache,
    cache_dir,
    caches_root,
    default_cache_dir,
)

__all__ = [
    "CACHE_ENV",
    "STAGE_CACHE_ENV",
    "CachePlan",
    "EntryInfo",
    "StageCache",
    "cache_dir",
    "cacheable_nodes",
    "caches_root",
    "code_fingerprint",
    "default_cache_dir",
    "file_hash",
]
