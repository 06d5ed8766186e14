"""The back-ends (paper Sec. III-E): stages over the GTSAM pose graph, its factors, and the odometry's corrections."""
