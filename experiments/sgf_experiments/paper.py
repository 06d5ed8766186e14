"""The paper's figures (Park et al., ICRA 2024, Tables 2-4) and its sequences in table order."""

from __future__ import annotations

#: The campus sequences, in the order of the paper's tables.
SEQUENCE_ORDER = ["campus_large_loop", "campus_reverse_slope", "campus_delivery", "campus_large_loop_night"]
#: The paper's Table 2 (ATE in m) per sequence: (odometry, ORB-SLAM3, odometry + SGF).
PAPER_TABLE2 = {
    "campus_large_loop": (292.966, 28.422, 9.482),
    "campus_reverse_slope": (140.532, 48.546, 14.384),
    "campus_delivery": (71.147, 19.828, 12.365),
    "campus_large_loop_night": (295.106, None, 11.540),
}
#: The paper's Table 3: detection, loop pairs found (reverse), loops closed (reverse).
PAPER_TABLE3 = {
    "campus_large_loop": ("79/94", "33/34 (3/3)", "31 (1)"),
    "campus_reverse_slope": ("37/46", "11/16 (11/16)", "7 (7)"),
    "campus_delivery": ("19/23", "1/1 (1/1)", "1 (1)"),
}
#: The paper's Table 4: ATE (m) with MC-IPM and with plain IPM.
PAPER_TABLE4 = {"campus_large_loop": (9.482, 12.567), "campus_reverse_slope": (14.384, 67.625)}
