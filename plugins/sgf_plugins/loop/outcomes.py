"""The outcomes of the matches the loop stage decides on (the ``outcome`` column of ``loop_candidates.csv``)."""

from __future__ import annotations

#: A loop the stage emits.
ACCEPTED = "accepted"
#: A match into a symmetric group, which gives no loop here.
SYMMETRIC = "symmetric"
#: A match among look-alike groups (a tie, an aliased pattern) that nothing told apart.
AMBIGUOUS = "ambiguous"
#: The two views are of the same pass (too close in frames, time or path).
SEPARATION = "separation"
#: One of the two SGFs has too few points for ICP.
TOO_FEW_POINTS = "too_few_points"
#: No ICP fit passed the shape tests.
ICP = "icp"
#: No fit within the gate.
GATE = "gate"
#: Too few neighbouring SGFs agree with the loop.
CONSENSUS = "consensus"
#: More than one fit within the gate.
NOT_UNIQUE = "not_unique"
#: A match into a prior map, held until enough of them agree on where the run is in the map.
MAP_UNCONFIRMED = "map_unconfirmed"

#: The reasons a match gives no loop, each counted (``metrics.json`` loops.rejected).
REFUSALS = (
    SYMMETRIC,
    AMBIGUOUS,
    SEPARATION,
    TOO_FEW_POINTS,
    ICP,
    GATE,
    CONSENSUS,
    NOT_UNIQUE,
    MAP_UNCONFIRMED,
)
#: Every outcome a row of ``loop_candidates.csv`` can have.
OUTCOMES = (ACCEPTED, *REFUSALS)
