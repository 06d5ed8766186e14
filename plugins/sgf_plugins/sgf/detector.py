"""The moment-based SGF detector (paper Sec. III-B, eq. 5-8): one selected SGF per ground feature per pass."""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any, Literal

import numpy as np
from pydantic import Field, model_validator

from sgf_pipeline import RunContext, Stage, StageParams, StageRegistry, hookimpl
from sgf_pipeline.types import Bev, BevGrid, Frame, SaliencyMap, SalientGroundFeature, SgfDetections
from sgf_plugins.sgf.best_view import best_view, group_views
from sgf_plugins.sgf.regions import Region, find_regions
from sgf_plugins.sgf.tracking import FeatureTrack, FeatureView, associate, moved_enough

log = logging.getLogger("sgf_pipeline.sgf")

_NO_PIXELS = np.zeros((0, 2), dtype=np.int32)


class HuWindowParams(StageParams):
    """Saliency binarisation, frame-to-frame tracking and Hu-moment view selection (Sec. III-B)."""

    threshold: float = Field(0.5, gt=0.0, lt=1.0, description="saliency at or above which a BEV pixel is salient")
    min_area: int = Field(150, ge=1, description="smallest candidate region (pixels)")
    closing: int = Field(
        0, ge=0, description="radius (px) of a morphological closing of the mask that joins fragments; 0 = none"
    )
    merge_distance: float = Field(
        0.3,
        ge=0.0,
        description="regions closer than this (m) form one SGF: the glyphs of a sign, the triangles of a give-way row "
        "(0 = every region its own SGF)",
    )
    hu_scale: Literal["raw", "log"] = Field(
        "raw",
        description="Hu invariants compared by eq. 8: raw h_j (the paper's formula), or sign(h) log10|h| (OpenCV)",
    )
    hu_threshold: float = Field(0.005, gt=0.0, description="eq. 8 distance below which consecutive views group")
    border_margin: int = Field(
        1, ge=1, description="a region within this many pixels of the image border or the invalid area touches it"
    )
    border_reach: Literal["region", "merge"] = Field(
        "merge",
        description="what must keep border_margin from the border for a view to have fully appeared: the region's "
        "pixels (the paper's test), or also the half merge_distance around them, where a further part of the same "
        "SGF would merge in (the cut-off end of a row of chevrons; docs/method.md)",
    )
    min_overlap: float = Field(
        0.3, gt=0.0, le=1.0, description="share of a view's predicted pixels on a region to continue its track"
    )
    max_centroid_distance: float = Field(
        0.3, ge=0.0, description="without overlap, largest predicted-centroid error (m) that still continues a track"
    )
    max_missed: int = Field(1, ge=0, description="frames a track may go unseen while predicted in view")
    min_track_views: int = Field(2, ge=1, description="views a valid feature range needs to give an SGF")
    group_choice: Literal["largest", "most_salient"] = Field(
        "largest",
        description="which group gives the SGF: the largest (ties: higher mean saliency) or the most salient",
    )
    view_choice: Literal["most_salient", "salient_near", "track_near"] = Field(
        "most_salient",
        description="the view that becomes the SGF: the chosen group's most salient (paper); among the group's views "
        "within near_margin of it the nearest to the camera (salient_near: the BEV is sharpest and most exact near "
        "the robot); or the nearest such view of the whole track (track_near: where every view is its own group)",
    )
    near_margin: float = Field(0.1, ge=0.0, le=1.0, description="saliency margin of salient_near and track_near")
    truth_min_fraction: float = Field(
        0.3, gt=0.0, le=1.0, description="share of a region a ground-truth marking must cover to label it"
    )
    min_view_motion: float = Field(
        0.01, ge=0.0, description="a track takes a new view only once the robot moved this far (m) since its last..."
    )
    min_view_turn: float = Field(
        0.01, ge=0.0, description="...or turned this much (rad); 0 in either of the two: a view every frame"
    )
    max_track_views: int = Field(
        1000, ge=2, description="a track with this many views is closed (its SGF selected) and a new one begins"
    )

    @model_validator(mode="after")
    def _check(self) -> HuWindowParams:
        if self.min_area < 3:
            raise ValueError("min_area must be at least 3 pixels: smaller regions have no shape")
        return self


class HuMomentDetector(Stage):
    """Select one SGF per physical ground feature per pass from the stream of saliency masks (eq. 5-8).

    1. Binarise the saliency (``threshold``) inside the camera's view, optionally close small gaps
       (``closing``), and keep connected regions of ``min_area`` pixels or more.
    2. Follow each feature over frames (its valid feature range): the last view's pixels are lifted
       to the ground (eq. 9), moved by the relative odometry and projected into the new BEV; a region
       continues the track when enough predicted pixels fall on it (``min_overlap``), or when the
       predicted centroid is within ``max_centroid_distance``. The range ends when the prediction
       leaves the view, or after ``max_missed`` frames without a region.
    3. Over the range, compute the Hu invariants (eq. 5-7) and the distance of each view to the
       previous one (eq. 8); views touching the image border or the boundary of ``Bev.valid`` are
       rejected (the feature is not wholly in view) and break groups (``border_reach=merge`` also
       rejects a view with the border within half ``merge_distance`` of it, where a further part of
       the same SGF, the next chevron of a row, may lie just out of view); the remaining consecutive
       views group while their distance stays below ``hu_threshold``.
    4. The SGF is the most salient view (highest mean saliency) of the largest group (ties go to the
       group of higher mean saliency): a shape seen the same way over the most frames is the feature
       wholly in view, while occluded or noisy views form small groups.

    A frame's output holds the SGFs whose range ended on that frame, so selections arrive late and
    carry their own frame index and odometry (``views`` counts the views of the whole range).
    Tracks still open when the sequence ends are dropped (``finalize`` cannot emit outputs) and
    counted in the metrics as ``open_at_end``.

    Long runs keep the detector's memory bounded: a track takes a new view only once the robot has
    moved ``min_view_motion`` or turned ``min_view_turn`` since the track's last view (a robot
    standing still for minutes sees nothing new; such frames are counted as ``stationary_views``),
    the pixels of a superseded view that touches the border are dropped (such a view is never
    selected), and a track that reaches ``max_track_views`` is closed and continued by a new one
    (``tracks_split``; a marking the robot circles around, a saliency map firing on the whole view).
    Candidate components below ``min_area`` are counted as ``regions_too_small``.

    Hu scale (the ambiguity of eq. 8): on ``raw`` invariants, consecutive wholly-visible views of
    rendered markings differ by a median 0.0011 (0.0024 with noisy masks), so the paper's 0.005
    groups 88 % (62 %) of them, while 86-93 % of entering or leaving pairs and all pairs of
    different markings (at least 0.064) stay apart. On ``log`` invariants (OpenCV's matchShapes)
    the near-zero h3..h7 flip sign and the same medians are 2-3.6, so 0.005 would never group two
    views (bench/bench_sgf.py, bench/RESULTS.md).
    """

    kind = "detector"
    name = "hu_window"
    output = "sgfs"
    Params = HuWindowParams

    def __init__(self, params: HuWindowParams) -> None:
        super().__init__(params)
        self.params: HuWindowParams = params
        self._tracks: list[FeatureTrack] = []
        self._selected: list[SalientGroundFeature] = []
        self._next_id = 0
        self._stats: dict[str, int] = {}

    def begin(self, context: RunContext) -> None:
        """Forget the tracks and selections of a previous sequence."""
        self._tracks = []
        self._selected = []
        self._next_id = 0
        self._stats = {
            "tracks": 0,
            "too_short": 0,
            "border_only": 0,
            "stationary_views": 0,
            "tracks_split": 0,
            "regions_too_small": 0,
        }

    @property
    def stats(self) -> dict[str, int]:
        """Counts so far: tracks started, ranges too short, ranges with only border views."""
        return dict(self._stats)

    @property
    def selected(self) -> list[SalientGroundFeature]:
        """Every SGF selected so far in this sequence."""
        return list(self._selected)

    # -- step 1: candidate regions ---------------------------------------------------------

    def regions(self, bev: Bev, saliency: SaliencyMap) -> tuple[np.ndarray, list[Region]]:
        """Label image and candidate regions of one frame (label k is ``regions[k - 1]``)."""
        p = self.params
        labels, regions, too_small = find_regions(
            bev,
            saliency,
            threshold=p.threshold,
            min_area=p.min_area,
            closing=p.closing,
            merge_distance=p.merge_distance,
            border_margin=p.border_margin,
            border_reach=p.border_reach,
            truth_min_fraction=p.truth_min_fraction,
        )
        self._stats["regions_too_small"] = self._stats.get("regions_too_small", 0) + too_small
        return labels, regions

    # -- steps 3-4: grouping and selection -------------------------------------------------

    def select(self, track: FeatureTrack, grid: BevGrid) -> SalientGroundFeature | None:
        """The SGF of a finished track: the most salient view of its chosen group, or None."""
        if len(track.views) < self.params.min_track_views:
            self._stats["too_short"] = self._stats.get("too_short", 0) + 1
            return None
        groups = group_views(track.views, self.params.hu_threshold, self.params.hu_scale)
        if not groups:
            self._stats["border_only"] = self._stats.get("border_only", 0) + 1
            return None

        best = best_view(groups, self.params.group_choice, self.params.view_choice, self.params.near_margin)
        region = best.region
        return SalientGroundFeature(
            track_id=track.track_id,
            frame_index=best.frame_index,
            timestamp=best.timestamp,
            odometry=best.odometry,
            pixels=region.pixels,
            grid=grid,
            saliency=region.saliency,
            hu=region.hu,
            views=len(track.views),
            instance_id=region.instance_id,
            homography=best.homography,
        )

    def process(self, frame: Frame, bev: Bev, saliency: SaliencyMap) -> SgfDetections:
        """Track this frame's salient regions and emit the SGFs of the features that left the view."""
        if bev.frame_index != frame.index:
            raise ValueError(f"BEV of frame {bev.frame_index} given with frame {frame.index}")
        odometry = np.asarray(frame.odometry, dtype=np.float64)
        if odometry.shape != (4, 4) or not np.all(np.isfinite(odometry)):
            raise ValueError(f"frame {frame.index}: odometry must be a finite 4x4 pose, got shape {odometry.shape}")
        labels, regions = self.regions(bev, saliency)
        valid = np.asarray(bev.valid, dtype=bool)
        matches, left = associate(
            self._tracks,
            labels,
            regions,
            valid,
            odometry,
            bev.grid,
            self.params.min_overlap,
            self.params.max_centroid_distance,
        )
        finished: list[FeatureTrack] = []
        still_open: list[FeatureTrack] = []
        for t, track in enumerate(self._tracks):
            if t in matches:
                track.missed = 0
                if not moved_enough(
                    track.last.odometry, odometry, self.params.min_view_motion, self.params.min_view_turn
                ):
                    self._stats["stationary_views"] = self._stats.get("stationary_views", 0) + 1
                    still_open.append(track)
                    continue
                last = track.last
                if last.region.touches_border and len(last.region.pixels):
                    # A border view is never selected; only the newest view's pixels predict the next frame.
                    track.views[-1] = replace(last, region=replace(last.region, pixels=_NO_PIXELS))
                track.views.append(
                    FeatureView(frame.index, frame.timestamp, odometry, regions[matches[t]], bev.homography)
                )
                if len(track.views) >= self.params.max_track_views:
                    self._stats["tracks_split"] = self._stats.get("tracks_split", 0) + 1
                    finished.append(track)
                    successor = FeatureTrack(self._next_id, [track.views[-1]])
                    self._next_id += 1
                    self._stats["tracks"] = self._stats.get("tracks", 0) + 1
                    still_open.append(successor)
                else:
                    still_open.append(track)
            elif t in left or track.missed >= self.params.max_missed:
                finished.append(track)
            else:
                track.missed += 1
                still_open.append(track)
        assigned = set(matches.values())
        for r, region in enumerate(regions):
            if r not in assigned:
                track = FeatureTrack(
                    self._next_id, [FeatureView(frame.index, frame.timestamp, odometry, region, bev.homography)]
                )
                self._next_id += 1
                self._stats["tracks"] = self._stats.get("tracks", 0) + 1
                still_open.append(track)
        self._tracks = still_open
        out = []
        for track in finished:
            sgf = self.select(track, bev.grid)
            if sgf is not None:
                out.append(sgf)
        self._selected.extend(sgf.without_pixels() for sgf in out)  # kept for the run's metrics: no pixels
        return SgfDetections(tuple(out))

    def finalize(self, context: RunContext) -> None:
        """Write ``sgf.detected``/``sgf.total`` (null without ground truth) and share the selected SGFs (no pixels)."""
        context.artifacts["sgf_selected"] = list(self._selected)
        sgf: dict[str, Any] = context.metrics.setdefault("sgf", {})
        sgf.update(
            {
                "selected": len(self._selected),
                "tracks": self._stats.get("tracks", 0),
                "rejected_short": self._stats.get("too_short", 0),
                "rejected_border": self._stats.get("border_only", 0),
                "stationary_views": self._stats.get("stationary_views", 0),
                "tracks_split": self._stats.get("tracks_split", 0),
                "regions_too_small": self._stats.get("regions_too_small", 0),
                "open_at_end": len(self._tracks),
                "detected": None,
                "total": None,
            }
        )
        truth = context.truth
        if truth is not None:
            on_path = truth.on_path
            found = {s.instance_id for s in self._selected if s.instance_id is not None}
            sgf["detected"] = len(on_path & found)
            sgf["total"] = len(on_path)
            sgf["false_selected"] = sum(1 for s in self._selected if s.instance_id is None)


@hookimpl
def sgf_register_stages(registry: StageRegistry) -> None:
    """Register the SGF detector."""
    registry.add(HuMomentDetector)
