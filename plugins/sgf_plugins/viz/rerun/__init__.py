"""A Rerun recording of a run (``sgf-run viz=rerun``): an observer on the lifecycle hooks, unknown to every stage.

Each keyframe is logged on two timelines, ``frame`` (its index) and ``time`` (its timestamp: a
duration, or a date when the dataset's clock is Unix time):

- ``camera/image``: the (enhanced) camera image, JPEG;
- ``bev/image``: the BEV at its own resolution, JPEG; ``bev/saliency``: the saliency map over it
  (a heat map at half opacity); ``bev/sgfs``: the outlines of the SGFs selected from that BEV,
  labelled with their track and group (logged at the frame of the view once the detector selects it);
- ``sgf/descriptor``: the polar descriptor of the newest SGF (rings x sectors), with the SGF's
  frame, track and group;
- ``map/*`` (2-D, x right and y up: y is logged negated) and ``world/*`` (3-D): ``odometry``,
  ``ground_truth`` (a segment per keyframe, shown from the start to the cursor), ``estimate``
  (the back-end's current estimate; ``map/robot`` its newest pose, heading as an arrow), ``correction``
  (arrows from poses to where the back-end moved them, shown on a frame that re-solves, at most 60)
  and ``loops/<n>``: row ``n`` of ``loop_candidates.csv``, a line
  between the estimated poses of its two frames in its outcome's colour, labelled with the outcome
  and its detail; ``log/loops`` and ``log/sgfs`` say the same as text;
- ``timing/<kind>``: each stage's milliseconds.

One frame after the last, the end of the run is logged: the final trajectory and its correction,
and the loops the end of the run decided or changed, so the recording ends as the run directory
does. The recording is written to ``<run dir>/run.partial.rrd`` and renamed ``run.rrd`` once the run
has finished (a failed run keeps the partial one); ``spawn``, ``connect`` and ``serve`` stream it to
a viewer as well. The logging runs on a thread of its own, ten keyframes at a time
(``bench/RESULTS.md`` has its cost); the pipeline's thread only hands the outputs over.
"""

from __future__ import annotations

from sgf_plugins.viz.rerun.observer import RerunObserver

_OBSERVER = RerunObserver()

# pluggy registers this package; the observer's hook implementations are its module-level names.
sgf_observer_options = _OBSERVER.sgf_observer_options
sgf_run_start = _OBSERVER.sgf_run_start
sgf_after_stage = _OBSERVER.sgf_after_stage
sgf_frame_end = _OBSERVER.sgf_frame_end
sgf_on_error = _OBSERVER.sgf_on_error
sgf_run_end = _OBSERVER.sgf_run_end
