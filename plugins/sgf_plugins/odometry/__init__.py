"""The ``odometry_scale`` stage: the wheel odometry's scale error and heading bias, measured from the camera."""
