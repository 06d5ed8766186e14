"""sgf-pipeline: salience-guided ground factors for robust localization of delivery robots.

The public API for plugin authors and embedding applications: the hook markers, the stage
contract, the registry and the pipeline runner.
"""

from sgf_pipeline.context import RunContext
from sgf_pipeline.errors import ConfigError, DataError, PipelineGraphError, PluginError, SgfError, StageError
from sgf_pipeline.hookspecs import hookimpl, hookspec
from sgf_pipeline.registry import load_plugins
from sgf_pipeline.runner import Pipeline, StepResult
from sgf_pipeline.stage import Dataset, Previous, Settlement, Stage, StageParams
from sgf_pipeline.variants import StageRegistry

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "DataError",
    "Dataset",
    "Pipeline",
    "PipelineGraphError",
    "PluginError",
    "Previous",
    "RunContext",
    "Settlement",
    "SgfError",
    "Stage",
    "StageError",
    "StageParams",
    "StageRegistry",
    "StepResult",
    "__version__",
    "hookimpl",
    "hookspec",
    "load_plugins",
]
