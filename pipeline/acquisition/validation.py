"""What a strategy returns, checked where the pick is made (built-ins and plugins alike).

A round asks a strategy for ``count`` picks from the candidates (``count`` is already at most the
views left in the budget and in the pool). Its ``Selection`` must hold exactly ``count`` ids, each a
candidate of this round, none already taken, none twice, and a score for candidates only, none of
them NaN. An infinite score is a rank, not a fault (COVER scores a candidate that sees none of the
model +inf, as its paper does); NaN orders nothing. A violation is a ``SelectionError`` naming the
strategy, the round and the offending ids: a deterministic fault of the strategy, never retried.
"""

from __future__ import annotations

import math
import numbers
from collections import Counter
from dataclasses import dataclass


class SelectionError(ValueError):
    """A strategy returned a selection the round cannot take; one line naming strategy, round, ids."""


@dataclass(frozen=True)
class RoundAsk:
    """What the round asked of the strategy: ``count`` picks among ``candidate_ids`` with ``taken_ids``
    already trained on."""

    strategy: str
    round: int
    count: int
    candidate_ids: tuple[int, ...]
    taken_ids: tuple[int, ...]


def _ids(values) -> str:
    shown = list(values)[:10]
    return "[" + ", ".join(str(v) for v in shown) + (", ..." if len(list(values)) > 10 else "") + "]"


def selection_problem(ask: RoundAsk, chosen: list, scores: dict) -> str | None:
    """Why the selection cannot be taken (None: it can)."""
    candidates, taken = set(ask.candidate_ids), set(ask.taken_ids)
    not_int = [c for c in chosen if isinstance(c, bool) or not isinstance(c, numbers.Integral)]
    if not_int:
        return f"picked {_ids(not_int)}, which are not view ids (integers)"
    again = sorted(c for c in set(chosen) if c in taken)
    if again:
        return f"picked view(s) {_ids(again)} already taken"
    outside = sorted(c for c in set(chosen) if c not in candidates)
    if outside:
        return f"picked view(s) {_ids(outside)} outside this round's {len(candidates)} candidates"
    twice = sorted(c for c, n in Counter(chosen).items() if n > 1)
    if twice:
        return f"picked view(s) {_ids(twice)} more than once in {_ids(chosen)}"
    if len(chosen) != ask.count:
        return f"returned {len(chosen)} pick(s) {_ids(chosen)}, asked for {ask.count}"
    unknown = sorted((k for k in scores if k not in candidates), key=str)
    if unknown:
        return f"scored view(s) {_ids(unknown)} that are not candidates of this round"
    nan = sorted((k for k, v in scores.items() if _not_a_number(v)), key=str)
    if nan:
        return f"scored view(s) {_ids(nan)} NaN (or not a number)"
    return None


def _not_a_number(value) -> bool:
    try:
        return math.isnan(float(value))
    except (TypeError, ValueError):
        return True


def check_selection(ask: RoundAsk, chosen: list, scores: dict) -> None:
    """Raise ``SelectionError`` when the selection breaks a rule of the module's text."""
    problem = selection_problem(ask, chosen, scores)
    if problem is not None:
        raise SelectionError(f"strategy {ask.strategy!r}, round {ask.round} ({len(ask.taken_ids)} views taken): "
                             f"{problem}")
