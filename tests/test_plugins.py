"""Plugin discovery and the registry: the stage contract is enforced when a plugin registers."""

from __future__ import annotations

import ast
import difflib
import inspect
import json
import re
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator
from sgf_testing import ROOT, run_cli

from sgf_pipeline import PluginError, Stage, StageRegistry, hookimpl, hookspecs, load_plugins
from sgf_pipeline.cli.plugins import REGENERATE
from sgf_pipeline.registry import ALLOW_ENV, BLOCK_ENV
from sgf_pipeline.types import CameraImage, Frame


class Good(Stage):
    """A valid stage."""

    kind = "enhance"
    name = "good"
    output = "image"

    def process(self, frame: Frame) -> CameraImage:
        return CameraImage(frame.image, frame.index)


class LooseParams(BaseModel):
    x: int = 1


class Loose(Good):
    """Params that accept unknown keys."""

    name = "loose"
    Params = LooseParams  # type: ignore[assignment]


class BadName(Good):
    """A variant name that is not an identifier."""

    name = "Bad-Name"


class NoReturn(Stage):
    """process without a return annotation."""

    kind = "enhance"
    name = "noreturn"
    output = "image"

    def process(self, frame: Frame):  # type: ignore[no-untyped-def]
        return frame


class Splat(Stage):
    """process with **kwargs."""

    kind = "enhance"
    name = "splat"
    output = "image"

    def process(self, **inputs: Frame) -> CameraImage:
        raise NotImplementedError


@pytest.mark.parametrize(
    ("cls", "message"),
    [
        (Loose, "Params must refuse unknown keys; derive it from StageParams"),
        (BadName, "name must be a lower-case identifier, got 'Bad-Name'"),
        (NoReturn, "has no return annotation"),
        (Splat, "must name its inputs"),
        (int, "is not a Stage or Dataset subclass"),
    ],
)
def test_registry_refuses_classes_that_break_the_contract(cls, message):
    with pytest.raises(PluginError, match=re.escape(message)):
        StageRegistry().add(cls)


def test_one_variant_registered_twice_by_two_plugins():
    class Other(Good):
        """Same kind and name as Good."""

    registry = StageRegistry()
    registry._scoped("first", None).add(Good)
    with pytest.raises(PluginError, match="registered twice: by first and by second"):
        registry._scoped("second", None).add(Other)


def test_first_party_plugins_come_through_the_entry_point_group():
    loaded = load_plugins()
    info = loaded.registry.get("enhance", "clahe")
    assert info.plugin == "enhance"
    assert info.distribution == "sgf-pipeline"
    assert info.signature.inputs[0].parameter == "frame"


def test_allow_and_block_lists(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv(BLOCK_ENV, "enhance")
    assert "enhance" not in load_plugins().registry.kinds()
    monkeypatch.delenv(BLOCK_ENV)
    monkeypatch.setenv(ALLOW_ENV, "enhance")
    assert "enhance" in load_plugins().registry.kinds()
    monkeypatch.setenv(ALLOW_ENV, "enhance,not_installed")
    with pytest.raises(PluginError, match="allowed plugin\\(s\\) not_installed are not installed"):
        load_plugins()


def test_a_plugin_that_fails_to_import_is_named(monkeypatch: pytest.MonkeyPatch):
    from importlib import metadata

    broken = metadata.EntryPoint(name="broken", value="no_such_module_xyz", group="sgf_pipeline")
    real = metadata.entry_points

    def fake(**kwargs):  # type: ignore[no-untyped-def]
        eps = list(real(**kwargs))
        return [*eps, broken] if kwargs.get("group") == "sgf_pipeline" else eps

    monkeypatch.setattr(metadata, "entry_points", fake)
    with pytest.raises(
        PluginError,
        match=r"plugin 'broken' \(no_such_module_xyz\).*failed to import.*SGF_PIPELINE_DISABLED_PLUGINS=broken",
    ):
        load_plugins()


class WatchOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")

    every: int = Field(1, ge=1)

    @model_validator(mode="after")
    def _not_thirteen(self) -> WatchOptions:
        if self.every == 13:
            raise ValueError("watch.every=13 is unlucky: choose another")
        return self


class Watcher:
    """An observer with a config node of its own (``watch``), seen by its hooks as ``run.observer_options``."""

    def __init__(self, node: str = "watch", model: type = WatchOptions) -> None:
        self.node, self.model = node, model
        self.seen: list[object] = []

    @hookimpl
    def sgf_observer_options(self) -> dict[str, type]:
        return {self.node: self.model}

    @hookimpl
    def sgf_run_start(self, run) -> None:  # type: ignore[no-untyped-def]
        self.seen.append(run.observer_options.get(self.node))


def test_an_observer_reads_its_own_config_node():
    from toy_stages import ToyPlugin

    from sgf_pipeline import ConfigError, Pipeline

    watcher = Watcher()
    plugins = load_plugins(extra=[("toy", ToyPlugin()), ("watcher", watcher)])
    assert plugins.observer_options["watch"] is WatchOptions
    config = {"pipeline": ["dataset"], "dataset": {"name": "figure_eight", "frames": 3}, "run": {"progress": False}}
    Pipeline.from_config({**config, "watch": {"every": 5}}, plugins=plugins).run()
    Pipeline.from_config(config, plugins=plugins).run()  # no node: the observer is told so
    assert watcher.seen == [WatchOptions(every=5), None]
    # validated while the pipeline is built: unknown keys, bad values and the model's own checks
    with pytest.raises(ConfigError, match=r"watch\.often: unknown parameter \(parameters of this variant: every\)"):
        Pipeline.from_config({**config, "watch": {"often": 2}}, plugins=plugins)
    with pytest.raises(ConfigError, match=r"watch\.every: Input should be greater than or equal to 1"):
        Pipeline.from_config({**config, "watch": {"every": 0}}, plugins=plugins)
    with pytest.raises(ConfigError, match=r"watch: watch\.every=13 is unlucky: choose another$"):
        Pipeline.from_config({**config, "watch": {"every": 13}}, plugins=plugins)
    # without the observer its node is a typo like any other
    with pytest.raises(ConfigError, match=r"unknown top-level key\(s\) \['watch'\]"):
        Pipeline.from_config({**config, "watch": {"every": 5}}, plugins=load_plugins(extra=[("toy", ToyPlugin())]))


@pytest.mark.parametrize(
    ("watchers", "message"),
    [
        ([Watcher("enhance")], "config node 'enhance' is taken by the runner or a stage kind"),
        ([Watcher("run")], "config node 'run' is taken by the runner or a stage kind"),
        ([Watcher("Watch")], "must be a lower-case identifier"),
        ([Watcher(model=LooseParams)], "must be a pydantic model refusing unknown keys"),
        ([Watcher(), Watcher()], "config node 'watch' is declared by plugins 'w0' and 'w1'"),
    ],
)
def test_observer_config_nodes_that_break_the_contract(watchers: list[Watcher], message: str):
    with pytest.raises(PluginError, match=re.escape(message)):
        load_plugins(extra=[(f"w{k}", w) for k, w in enumerate(watchers)])


class Misspelt:
    """An observer whose hook no hookspec declares (``sgf_run_started`` for ``sgf_run_start``)."""

    @hookimpl
    def sgf_run_started(self, run: object) -> None:
        raise AssertionError("never called")


def test_a_hook_no_hookspec_declares_fails_at_start_up_naming_plugin_and_hook():
    with pytest.raises(PluginError) as caught:
        load_plugins(allow=[], extra=[("misspelt", Misspelt())])
    message = str(caught.value)
    assert "plugin 'misspelt' implements hook 'sgf_run_started', which no hookspec declares" in message
    assert "the hooks are: " in message and "sgf_run_start" in message


def test_docs_configuration_is_what_sgf_plugins_generates():
    result = run_cli("sgf-plugins", "format=markdown")
    assert result.returncode == 0, result.stderr
    committed = (ROOT / "docs" / "configuration.md").read_text()
    if committed != result.stdout:
        diff = difflib.unified_diff(
            committed.splitlines(), result.stdout.splitlines(), "docs/configuration.md", "generated", lineterm=""
        )
        pytest.fail(
            f"docs/configuration.md is not what sgf-plugins generates; regenerate it with `{REGENERATE}`:\n"
            + "\n".join(list(diff)[:40])
        )
    assert "## `loop`" in committed and "| `run.keyframe_distance` | `float` |" in committed


def test_every_hookspec_is_documented():
    specs = [m for n, m in inspect.getmembers(hookspecs.PipelineHooks, inspect.isfunction) if n.startswith("sgf_")]
    assert len(specs) >= 7
    for spec in specs:
        doc = inspect.getdoc(spec) or ""
        assert doc.strip(), f"hookspec {spec.__name__} has no docstring"
        params = [p for p in inspect.signature(spec).parameters if p != "self"]
        for p in params:
            assert f":param {p}:" in doc, f"hookspec {spec.__name__} does not document parameter {p!r}"


def test_the_core_imports_no_plugin():
    offenders = []
    for path in (ROOT / "sgf_pipeline").rglob("*.py"):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            offenders += [
                f"{path.relative_to(ROOT)}: {n}" for n in names if n.split(".")[0] in ("sgf_plugins", "sgf_experiments")
            ]
    assert not offenders, offenders


def test_import_linter_contract_holds():
    result = run_cli("lint-imports", cwd=ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "The core never imports a plugin or an experiment KEPT" in result.stdout
    assert "The plugins never import an experiment KEPT" in result.stdout
    assert "The plugins' layers: viz, then independent stage packages, then shared KEPT" in result.stdout
    assert "The core's layers: each module imports only the ones below it KEPT" in result.stdout


def test_hookimpl_marker_is_the_projects():
    assert hookimpl.project_name == "sgf_pipeline"


def test_third_party_plugin_package_is_listed_and_selected_by_config(toy_plugin_site: Path, tmp_path: Path):
    env = {"PYTHONPATH": str(toy_plugin_site)}
    listing = run_cli("sgf-plugins", "format=json", env=env)
    assert listing.returncode == 0, listing.stderr
    entries = {(e["kind"], e["name"]): e for e in json.loads(listing.stdout)}
    gamma = entries[("enhance", "gamma")]
    assert gamma["distribution"] == "sgf-toy-plugin" and gamma["plugin"] == "toy"
    assert gamma["params"] == [
        {"name": "gamma", "type": "float", "default": 1.0, "description": "exponent applied to intensities in [0, 1]"}
    ]
    text = run_cli("sgf-plugins", "kind=enhance", env=env).stdout
    assert "enhance=gamma  -> image  from toy (sgf-toy-plugin)" in text

    run_dir = tmp_path / "run"
    result = run_cli(
        "sgf-run",
        "pipeline=[dataset,enhance]",
        "dataset=toy_circle",
        "enhance=gamma",
        "enhance.gamma=0.25",
        "run.progress=false",
        f"hydra.run.dir={run_dir}",
        env=env,
    )
    assert result.returncode == 0, result.stderr
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["stages"] == {"dataset": "toy_circle", "enhance": "gamma"}
    assert metrics["timing"]["frames"] == 40
    # Odometry is the circle scaled by 1.02 (radius 5.0 -> 5.1): after alignment every error is 0.1 m.
    assert metrics["ate_rmse_m"]["odometry"] == pytest.approx(0.1, abs=2e-3)
    effective = (run_dir / "config.yaml").read_text()
    assert "gamma: 0.25" in effective
    assert "ATE odometry (m)            0.10" in result.stdout
    # The plugin ships no YAML for its variants (their defaults come from their Params), and one
    # preset in its config package: enhance=gamma_dark is the gamma variant at 0.5.
    composed = run_cli("sgf-run", "--cfg", "job", "dataset=toy_circle", "enhance=gamma_dark", env=env)
    assert composed.returncode == 0, composed.stderr
    node = yaml.safe_load(composed.stdout)
    assert node["enhance"] == {"name": "gamma", "gamma": 0.5}
    assert node["dataset"] == {"name": "toy_circle", "frames": 40, "radius": 5.0, "seed": 0, "mark_file": ""}

    # Without the plugin on the path, the same config fails with Hydra's list of options.
    missing = run_cli("sgf-run", "pipeline=[dataset,enhance]", "dataset=toy_circle", f"hydra.run.dir={tmp_path / 'x'}")
    assert missing.returncode != 0
    assert "Could not find 'dataset/" in missing.stderr


def test_cli_reports_config_errors_without_a_traceback(toy_plugin_site: Path, tmp_path: Path):
    env = {"PYTHONPATH": str(toy_plugin_site)}
    result = run_cli(
        "sgf-run",
        "pipeline=[dataset,enhance]",
        "dataset=toy_circle",
        "enhance=clahe",
        "enhance.clip_limit=-2",
        f"hydra.run.dir={tmp_path}",
        env=env,
    )
    assert result.returncode == 2
    assert "error: invalid parameters for enhance=clahe" in result.stderr
    assert "enhance.clip_limit: Input should be greater than 0" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "metrics.json").exists()


def test_sigterm_during_a_run_leaves_a_record_and_no_half_file(toy_plugin_site: Path, tmp_path: Path):
    import os
    import signal
    import subprocess
    import sys
    import time

    run_dir = tmp_path / "run"
    mark = tmp_path / "frames_flow"
    env = dict(os.environ, PYTHONPATH=str(toy_plugin_site))
    proc = subprocess.Popen(
        [
            str(Path(sys.executable).parent / "sgf-run"),
            "pipeline=[dataset,enhance]",
            "dataset=toy_circle",
            "dataset.frames=1000000",
            f"dataset.mark_file={mark}",
            "run.keyframe_distance=0",  # every frame a keyframe: the reading thread's lead bounds the frames unprocessed
            "enhance=clahe",
            "run.progress=false",
            f"hydra.run.dir={run_dir}",
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    # Frame 20 is read only after frames went through the stages: the reading thread holds a few
    # keyframes ahead (READ_DEPTH), never twenty, and every frame is a keyframe here.
    from sgf_pipeline.reading import READ_DEPTH

    assert READ_DEPTH + 2 < 20
    deadline = time.time() + 120
    while not mark.exists():
        assert time.time() < deadline and proc.poll() is None, proc.communicate()
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=60)
    assert proc.returncode != 0
    failure = json.loads((run_dir / "failure.json").read_text())
    assert failure["status"] == "interrupted"
    assert failure["frames_processed"] > 0
    assert not (run_dir / "metrics.json").exists()
    assert not [p for p in run_dir.iterdir() if p.name.endswith(".part")]
