"""Timed pose sequences and their file formats: TUM, KITTI (with a times file) and EuRoC state CSV.

Every reader checks what evo would silently accept or reject late: each line's field count,
finite numbers, strictly increasing timestamps, unit quaternions (within
:data:`QUATERNION_TOLERANCE`), rotation matrices (within :data:`ROTATION_TOLERANCE`), and a last
line that ends (a file cut off mid-number does not); errors name the file and line. Writers are
atomic. ``read_trajectory``/``write_trajectory`` pick the format from a name or the file.

Formats:

* TUM: ``timestamp tx ty tz qx qy qz qw`` (seconds; ``#`` comments).
* KITTI: 12 numbers per line, the row-major 3x4 pose; no timestamps in the file. The times
  come from a separate file (one number per line, KITTI's ``times.txt``); without one the
  timestamps are the row numbers 0, 1, 2, ... so that two KITTI files pair up row by row.
* EuRoC: ``#timestamp [ns],p_RS_R_x [m],p_RS_R_y,p_RS_R_z,q_RS_w [],q_RS_x,q_RS_y,q_RS_z[,...]``
  (integer nanoseconds, quaternion w first; the velocity and bias columns of
  ``state_groundtruth_estimate0/data.csv`` are read past and not written).

Modules: :mod:`~sgf_pipeline.trajectory.model` (the Trajectory type), :mod:`~sgf_pipeline.trajectory.checks`
(what the readers check), :mod:`~sgf_pipeline.trajectory.tum`, :mod:`~sgf_pipeline.trajectory.kitti` and
:mod:`~sgf_pipeline.trajectory.euroc` (one format each) and :mod:`~sgf_pipeline.trajectory.formats` (any format).
"""

from sgf_pipeline.trajectory.checks import QUATERNION_TOLERANCE, ROTATION_TOLERANCE, checked_trajectory
from sgf_pipeline.trajectory.euroc import read_euroc_csv, seconds_from_ns, write_euroc_csv
from sgf_pipeline.trajectory.formats import detect_format, read_trajectory, write_trajectory
from sgf_pipeline.trajectory.kitti import read_kitti, read_times, write_kitti
from sgf_pipeline.trajectory.model import FORMATS, Duplicates, Trajectory, TrajectoryError, TrajectoryFormat
from sgf_pipeline.trajectory.tum import parse_tum, read_tum, write_tum

__all__ = [
    "FORMATS",
    "QUATERNION_TOLERANCE",
    "ROTATION_TOLERANCE",
    "Duplicates",
    "Trajectory",
    "TrajectoryError",
    "TrajectoryFormat",
    "checked_trajectory",
    "detect_format",
    "parse_tum",
    "read_euroc_csv",
    "read_kitti",
    "read_times",
    "read_trajectory",
    "read_tum",
    "seconds_from_ns",
    "write_euroc_csv",
    "write_kitti",
    "write_trajectory",
    "write_tum",
]
