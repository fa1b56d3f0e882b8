"""The fixed validation suites split into a tuning half and a held-back half (issue 23, item 5).

A diagnosis tuned while looking at the cases that then report its figures measures its own tuning. Every
case of :mod:`.hidden` (its effects and null bases) and of :mod:`.unseen` is assigned once, by a hash of its
name, to the "tuning" half (the cases one may look at while changing the diagnosis) or the "heldback" half
(reported, never looked at while tuning). The assignment depends on the name alone: adding a case never moves
another one, and the same name is in the same half on every machine and every run.
"""

from __future__ import annotations

import hashlib

HALVES = ("tuning", "heldback")


def half_of(name: str) -> str:
    """The half of the case ``name``: the parity of the first byte of sha256("newtsim-half:" + name)."""
    digest = hashlib.sha256(f"newtsim-half:{name}".encode()).digest()
    return HALVES[digest[0] & 1]


def select(names, half: str | None) -> list[str]:
    """The names of ``names`` in ``half`` (all of them, in order, for None or "all")."""
    if half in (None, "all"):
        return list(names)
    if half not in HALVES:
        raise ValueError(f"half {half!r}: expected one of {', '.join(HALVES)} or all")
    return [n for n in names if half_of(n) == half]
