"""The first-party plugins of sgf-pipeline, each registered through the ``sgf_pipeline`` entry points."""
