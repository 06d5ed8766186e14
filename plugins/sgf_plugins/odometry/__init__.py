"""Wheel odometry as the pipeline reads it: frame log, loop-anchored distances, drift model, scale."""
