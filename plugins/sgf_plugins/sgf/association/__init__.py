"""Online grouping of SGF descriptors (paper Sec. III-C, eq. 9-10)."""
