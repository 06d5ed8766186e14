"""A third-party plugin: a gamma enhancement and a small circular test sequence."""
