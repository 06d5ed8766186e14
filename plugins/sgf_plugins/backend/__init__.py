"""The back-ends (paper Sec. III-E): the GTSAM pose graph and the heading bias it estimates."""
