"""What several stage packages use; it imports no stage package.

Planar rigid transforms (:mod:`~sgf_plugins.shared.se2`), the polar descriptor's maths
(:mod:`~sgf_plugins.shared.polar`), the odometry's frame log, drift model and loop-anchored
distances (:mod:`~sgf_plugins.shared.frame_log`, :mod:`~sgf_plugins.shared.drift`,
:mod:`~sgf_plugins.shared.anchoring`), the heading-bias estimator
(:mod:`~sgf_plugins.shared.heading_bias`), and the BEV a camera sees
(:mod:`~sgf_plugins.shared.bev_homography`, :mod:`~sgf_plugins.shared.bev_region`).
"""
