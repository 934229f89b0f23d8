"""The constraint vocabulary of every declared field: the library's configs (``RefineConfig``,
``TrackerConfig``, ``FusionConfig``, ``Oracle``), the messages (``common.runtime.messages``) and
the nodes' params. Each is a msgspec ``Meta`` on the field (``Annotated[float, Meta(gt=0)]``)
with the words of the refusal as its ``description`` (``{value}``: the value refused); a number
is finite and within ``MAX_NUMBER`` (the messages' range, ``common.runtime.checks.MAX_COORD``).

The runtime reads the same annotations (``common.runtime.schema``, ``common.runtime.params``): a
message field, or a node param, that breaks one is refused in the same words, a param where the
graph sets it (``needletrack validate``). ``check_fields`` refuses a config built in code. Imports
nothing of ``common``, so the geometry and the runtime share it without importing each other.
"""
from __future__ import annotations

import dataclasses
import functools
import types
import typing
from typing import Annotated

import msgspec

MAX_NUMBER = 1e7
"""The largest magnitude of a number any field takes (finite: NaN and inf are beyond it)."""

PositiveNumber = Annotated[float, msgspec.Meta(gt=0, le=MAX_NUMBER, description="must be a positive number, got {value}")]
"""A finite number > 0."""

NonNegativeNumber = Annotated[float, msgspec.Meta(ge=0, le=MAX_NUMBER, description="must be >= 0, got {value}")]
"""A finite number >= 0."""

Probability = Annotated[float, msgspec.Meta(ge=0, le=1, description="must be a probability in [0, 1], got {value}")]
"""A number in [0, 1]."""


def text_matching(pattern: str, what: str) -> type:
    """A string matching ``pattern`` (a regular expression), refused as not ``what``."""
    return Annotated[str, msgspec.Meta(pattern=pattern, description=f"must be {what}, got {{value!r}}")]


class Required:
    """The mark of a param that a graph must set (``required``): its default (empty) stands for
    "not given", and a graph without it is refused where it declares the node."""

    def __init__(self, what: str):
        self.what = what

    def __repr__(self) -> str:
        return f"Required({self.what!r})"


def required(what: str) -> type:
    """A non-empty string that must be given (``what`` it is, for the refusal)."""
    return Annotated[str, msgspec.Meta(min_length=1, description=f"is required ({what})"), Required(what)]


def required_fields(cls) -> dict:
    """``{name: what}`` of the dataclass ``cls``'s fields marked ``required``."""
    hints = typing.get_type_hints(cls, include_extras=True)
    out = {}
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if typing.get_origin(tp) is Annotated:
            mark = next((m for m in tp.__metadata__ if isinstance(m, Required)), None)
            if mark is not None:
                out[f.name] = mark.what
    return out


def at_least(lo: int) -> type:
    """An int >= ``lo``."""
    return Annotated[int, msgspec.Meta(ge=lo, description=f"must be at least {lo}, got {{value}}")]


def number_at_least(lo: float) -> type:
    """A finite number >= ``lo``."""
    return Annotated[float, msgspec.Meta(ge=lo, le=MAX_NUMBER, description=f"must be at least {lo:g}, got {{value}}")]


def in_range(lo: float, below: float) -> type:
    """A number in ``[lo, below)``."""
    return Annotated[float, msgspec.Meta(ge=lo, lt=below, description=f"must be in [{lo:g}, {below:g}), got {{value}}")]


@functools.lru_cache(maxsize=None)
def _constrained(cls) -> tuple:
    """``(name, type, words)`` of ``cls``'s fields that carry a ``Meta``, in declared order."""
    hints = typing.get_type_hints(cls, include_extras=True)
    out = []
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if typing.get_origin(tp) in (typing.Union, types.UnionType):      # Optional[...]: its other type
            tp = next(a for a in typing.get_args(tp) if a is not type(None))
        if typing.get_origin(tp) is not Annotated:
            continue
        meta = next((m for m in tp.__metadata__ if isinstance(m, msgspec.Meta)), None)
        if meta is not None:
            out.append((f.name, tp, meta.description))
    return tuple(out)


def check_fields(obj, where: str = "{owner}.{name}: {why}") -> None:
    """ValueError for the first field of the dataclass ``obj`` that breaks its declared
    constraint, placed by ``where`` (``owner``: the class's name, ``name``, ``why``)."""
    for name, tp, words in _constrained(type(obj)):
        value = getattr(obj, name)
        if value is None:                 # an Optional field left out
            continue
        try:
            msgspec.convert(value.item() if hasattr(value, "item") else value, tp)   # numpy scalars as Python's
        except msgspec.ValidationError as exc:
            why = words.format(value=value) if words else str(exc)
            raise ValueError(where.format(owner=type(obj).__name__, name=name, why=why)) from None
