"""Loop closing (paper Sec. III-D): ICP fits, the gate, the consensus, the end-of-run checks."""
