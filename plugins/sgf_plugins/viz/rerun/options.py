"""Where a Rerun recording of a run goes (config node ``viz``), and the rerun-sdk it needs."""

from __future__ import annotations

from importlib import metadata
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

#: The config node of the observer's options.
NODE = "viz"
#: The recording of a finished run, and of one still running or failed.
RECORDING = "run.rrd"
PARTIAL_RECORDING = "run.partial.rrd"
#: The rerun-sdk minor version this recording is written for (its API changes between minor versions).
RERUN_VERSION = (0, 41)


def rerun_missing() -> str | None:
    """Why the installed rerun-sdk cannot write the recording, saying how to install it; None when it can."""
    wanted = ".".join(map(str, RERUN_VERSION))
    install = "install it with pip install 'sgf-pipeline[viz]' (in a checkout: scripts/setup.sh --dev)"
    try:
        version = metadata.version("rerun-sdk")
    except metadata.PackageNotFoundError:
        return (
            f"viz=rerun needs the rerun-sdk package ({wanted}, on Python 3.11 or later), which is not installed: "
            f"{install}, or run without viz=rerun"
        )
    if tuple(int(p) for p in version.split(".")[:2] if p.isdigit()) != RERUN_VERSION:
        return f"viz=rerun is written for rerun-sdk {wanted}, and {version} is installed: {install}"
    return None


class RerunOptions(BaseModel):
    """Where the recording goes (config node ``viz``: ``sgf-run viz=rerun``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: Literal["rerun"] = Field("rerun", description="the viewer")
    save: bool = Field(True, description="write <run dir>/run.rrd")
    spawn: bool = Field(False, description="open a local Rerun viewer and stream to it")
    connect: str | None = Field(
        None, description="stream to a running viewer at this address: host:port, or a rerun+http://.../proxy URL"
    )
    serve: bool = Field(False, description="serve the recording and the web viewer while the run lasts")
    grpc_port: int = Field(9876, ge=1, le=65535, description="port of the spawned viewer, or of the served recording")
    web_port: int = Field(9090, ge=1, le=65535, description="port of the served web viewer")

    @field_validator("connect")
    @classmethod
    def _viewer_url(cls, value: str | None) -> str | None:
        """``host:port`` becomes the viewer's URL; a URL must be one the Rerun SDK connects to."""
        if value is None:
            return None
        if "://" not in value:
            return f"rerun+http://{value}/proxy"
        if not value.startswith(("rerun://", "rerun+http://", "rerun+https://")):
            raise ValueError("a viewer's address is host:port or a rerun://, rerun+http:// or rerun+https:// URL")
        return value

    @model_validator(mode="after")
    def _usable(self) -> RerunOptions:
        """rerun-sdk is installed, and the viewer's ports are taken once."""
        problem = rerun_missing()
        if problem is not None:
            raise ValueError(problem)
        if self.spawn and self.serve:
            raise ValueError("viz.spawn and viz.serve would both listen on viz.grpc_port: choose one of them")
        return self
