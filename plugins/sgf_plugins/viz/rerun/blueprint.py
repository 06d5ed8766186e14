"""The layout of the Rerun viewer that opens a recording of a run."""

from __future__ import annotations

from typing import Any


def blueprint() -> Any:
    """The layout a newcomer sees: camera and BEV, the map (2-D and 3-D), stage times and the events' log."""
    import rerun.blueprint as rrb

    def shown(start: Any) -> Any:
        return rrb.VisibleTimeRanges(
            [
                rrb.VisibleTimeRange(timeline, start=start, end=rrb.TimeRangeBoundary.cursor_relative())
                for timeline in ("frame", "time")
            ]
        )

    ever, now = shown(rrb.TimeRangeBoundary.infinite()), shown(rrb.TimeRangeBoundary.cursor_relative())
    drawn: dict[str, Any] = {}  # odometry and truth from the start to the cursor; corrections at their frame
    for root in ("map", "world"):
        drawn.update({f"{root}/odometry": ever, f"{root}/ground_truth": ever, f"{root}/correction": now})
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(origin="camera", name="camera"),
                rrb.Spatial2DView(origin="bev", name="BEV, saliency and SGFs", overrides={"bev/sgfs": now}),
                rrb.TensorView(origin="sgf/descriptor", name="SGF descriptor (rings x sectors)"),
                row_shares=[3, 3, 2],
            ),
            rrb.Tabs(
                rrb.Spatial2DView(
                    origin="map", name="map (x right, y up)", overrides={k: v for k, v in drawn.items() if "map" in k}
                ),
                rrb.Spatial3DView(
                    origin="world", name="3-D", overrides={k: v for k, v in drawn.items() if "world" in k}
                ),
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="timing", name="stage times (ms)"),
                rrb.TextLogView(origin="log", name="SGFs and loop candidates"),
            ),
            column_shares=[2, 3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline="frame", play_state="following"),  # a saved run opens at its end
    )
