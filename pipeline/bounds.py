"""Declared bounds: a configurable value's type and range, written once next to its default.

A typed config declares a field with ``bounded(default, INT, ge=0, le=3)`` instead of a bare
default; ``violations(cls, data, where)`` checks a plain mapping (a config section) against every
declared field of ``cls`` (nested dataclasses included) and returns one line per bad value, naming
the dotted key, the value and what is allowed. The same declaration documents the key
(``Bound.describe``) and generates the tests' bad values (``Bound.bad_values``), so no key has a
hand-written check of its own.
"""

from __future__ import annotations

import math
import re
from dataclasses import MISSING, dataclass, field, fields, is_dataclass

INT, FLOAT, BOOL, STR = "integer", "number", "boolean", "string"
KINDS = (INT, FLOAT, BOOL, STR)


@dataclass(frozen=True)
class Bound:
    """What a value may be: ``kind`` (one of KINDS), inclusive/exclusive limits, a closed set of
    ``choices``, ``nullable`` (null allowed), ``pattern`` (a string's regular expression, with
    ``pattern_hint`` saying it in words), ``also``: literal strings accepted besides (e.g. "all"),
    and ``usual_max``: above it the value is allowed but a plan warns that it is far beyond
    anything measured."""

    kind: str
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple | None = None
    nullable: bool = False
    pattern: str | None = None
    pattern_hint: str | None = None
    also: tuple[str, ...] = ()
    usual_max: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"Bound.kind must be one of {KINDS}, got {self.kind!r}")

    def describe(self) -> str:
        """The allowed values in words, e.g. 'an integer in [0, 3]' or 'one of cpu, cuda'."""
        if self.choices is not None:
            text = "one of " + ", ".join(str(c) for c in self.choices)
        else:
            text = {INT: "an integer", FLOAT: "a number", BOOL: "true or false", STR: "a non-empty string"}[self.kind]
            low = f"[{_num(self.ge)}" if self.ge is not None else f"({_num(self.gt)}" if self.gt is not None else None
            high = f"{_num(self.le)}]" if self.le is not None else f"{_num(self.lt)})" if self.lt is not None else None
            if low and high:
                text += f" in {low}, {high}"
            elif low:
                text += f" >{'=' if self.ge is not None else ''} {_num(self.ge if self.ge is not None else self.gt)}"  # type: ignore[arg-type]  # low: one of them is set
            elif high:
                text += f" <{'=' if self.le is not None else ''} {_num(self.le if self.le is not None else self.lt)}"  # type: ignore[arg-type]  # high: one of them is set
            if self.pattern_hint:
                text += f" ({self.pattern_hint})"
        return text + (", or null" if self.nullable else "") + "".join(f' or "{a}"' for a in self.also)

    def problem(self, value) -> str | None:
        """None when ``value`` is allowed, else what is wrong with it."""
        if value is None:
            return None if self.nullable else "may not be null"
        if isinstance(value, str) and value in self.also:
            return None
        if self.choices is not None:
            return None if any(value == c and type(value) is type(c) for c in self.choices) else "not allowed"
        if not _is_kind(value, self.kind):
            return "wrong type"
        if self.kind in (INT, FLOAT):
            if isinstance(value, float) and not math.isfinite(value):
                return "not finite"
            if ((self.ge is not None and value < self.ge) or (self.gt is not None and value <= self.gt)
                    or (self.le is not None and value > self.le) or (self.lt is not None and value >= self.lt)):
                return "out of range"
        if self.kind == STR:
            if not value.strip():
                return "empty"
            if self.pattern is not None and not re.fullmatch(self.pattern, value):
                return "malformed"
        return None

    def bad_values(self) -> list:
        """Values this bound refuses: below and above the range, the wrong type, null where not
        allowed (the table-driven test runs every one of them through the config check)."""
        out: list = []
        step = 1 if self.kind == INT else 1e-3
        if self.ge is not None:
            out.append(_as_kind(self.ge - step, self.kind))
        if self.gt is not None:
            out.append(_as_kind(self.gt, self.kind))
        if self.le is not None:
            out.append(_as_kind(self.le + step, self.kind))
        if self.lt is not None:
            out.append(_as_kind(self.lt, self.kind))
        out.append("abc" if self.kind != STR else 7)
        if self.kind == STR and self.choices is None:
            out.append("")
        if self.choices is not None and self.kind == STR:
            out.append("no-such-choice")
        if not self.nullable:
            out.append(None)
        return out


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


def _as_kind(x: float, kind: str):
    return int(x) if kind == INT else float(x)


def _is_kind(value, kind: str) -> bool:
    if kind == BOOL:
        return isinstance(value, bool)
    if isinstance(value, bool):
        return False
    if kind == INT:
        return isinstance(value, int)
    if kind == FLOAT:
        return isinstance(value, (int, float))
    return isinstance(value, str)


def bounded(default, kind: str, **limits):
    """A dataclass field with ``default`` and its declared ``Bound(kind, **limits)``."""
    meta = {"bound": Bound(kind, **limits)}
    if isinstance(default, (list, dict, set)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


def bound_of(f) -> Bound | None:
    return f.metadata.get("bound")


def _default(f):
    """A field's default value (its factory's product), MISSING when it has none."""
    if f.default is not MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not MISSING else MISSING


def declared(cls, where: str = "") -> list[tuple[str, Bound, object]]:
    """Every declared key of ``cls`` (nested dataclass fields as dotted keys): (key, bound, default)."""
    out = []
    for f in fields(cls):
        default = _default(f)
        if is_dataclass(default):
            out += declared(type(default), f"{where}{f.name}.")
        elif (bound := bound_of(f)) is not None:
            out.append((f"{where}{f.name}", bound, default))
    return out


def present(cls, data: dict, where: str = ""):
    """(dotted key, bound, value) of each value of ``data`` (a plain mapping, maybe partial) that
    ``cls`` declares, nested groups walked; keys ``cls`` does not declare are skipped (unknown
    keys have their own check)."""
    by_name = {f.name: f for f in fields(cls)}
    for key, value in (data or {}).items():
        f = by_name.get(key)
        if f is None:
            continue
        default = _default(f)
        if is_dataclass(default) and isinstance(value, dict):
            yield from present(type(default), value, f"{where}{key}.")
        elif bound_of(f) is not None:
            yield f"{where}{key}", bound_of(f), value


def problem_lines(items) -> list[str]:
    """'<key>: <value> is not <what is allowed>' for each (key, bound, value) the bound refuses."""
    return [f"{key}: {value!r} is not {bound.describe()}" for key, bound, value in items
            if bound.problem(value) is not None]


def warning_lines(items) -> list[str]:
    """A line for each (key, bound, value) allowed but above the bound's ``usual_max``."""
    return [f"{key}={value!r} is far above anything measured (usually <= {_num(bound.usual_max)})"
            for key, bound, value in items
            if bound.usual_max is not None and bound.problem(value) is None and _is_kind(value, FLOAT)
            and value > bound.usual_max]


def violations(cls, data: dict, where: str = "") -> list[str]:
    """One line per value of ``data`` that breaks its declared bound in ``cls``."""
    return problem_lines(present(cls, data, where))


def warnings(cls, data: dict, where: str = "") -> list[str]:
    """Allowed values of ``data`` above their declared ``usual_max``: one line each (for a plan)."""
    return warning_lines(present(cls, data, where))


def _plain(obj) -> dict:
    """A dataclass's fields as a mapping, nested dataclasses as nested mappings (no deep copy)."""
    out = {}
    for f in fields(obj):
        if not f.init:  # derived in __post_init__, maybe not yet
            continue
        value = getattr(obj, f.name)
        out[f.name] = _plain(value) if is_dataclass(value) else value
    return out


def require_bounds(obj) -> None:
    """Raise ValueError naming every field of ``obj`` (a dataclass instance) that breaks its
    declared bound, nested groups as dotted keys: the one check every typed config calls."""
    problems = violations(type(obj), _plain(obj))
    if problems:
        raise BoundsError(problems)


class BoundsError(ValueError):
    """Values that break their declared bounds; ``problems`` holds one line per key, and
    ``under(prefix)`` the same lines with the section's dotted prefix in front of every key."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("; ".join(problems))
        self.problems = list(problems)

    def under(self, prefix: str) -> str:
        return "; ".join(prefix + p for p in self.problems)


def under(err: ValueError | TypeError, prefix: str) -> str:
    """An error's message with ``prefix`` before each key it names (a BoundsError's every line)."""
    return err.under(prefix) if isinstance(err, BoundsError) else f"{prefix}{err}"
