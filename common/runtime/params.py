"""Typed node params: a node declares them once as a dataclass, the graph's YAML fills them.

A node class sets ``Params`` to a dataclass whose fields are its params, each with a type and a
default::

    @dataclass
    class Params:
        min_score: float = 0.5            # keypoints scoring lower are not used
        stride: int | Literal["auto"] = "auto"

``parse_params(Params, raw, where)`` returns the instance, or raises ``ParamError`` listing every
unknown name and every value of the wrong type with its place, e.g.
``nodes[2].params.threads: expected int, got 'five'``. ``param_errors`` gives the same list
without raising (``needletrack validate`` reports them all). Types understood: ``int``, ``float``
(an int is accepted), ``bool``, ``str``, ``dict``, ``list[T]``, ``tuple[T, ...]``,
``Literal[...]``, unions (``X | None``). No coercion of strings: ``'5'`` is not an int.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from typing import Any, Literal, Mapping, Union

from common.errors import NeedletrackError


class ParamError(NeedletrackError, ValueError):
    """Params that do not match a node's schema; ``errors`` lists each with its place."""

    def __init__(self, errors: list[str]):
        super().__init__("; ".join(errors))
        self.errors = list(errors)


def _describe(tp) -> str:
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        return " or ".join(_describe(a) for a in typing.get_args(tp))
    if origin is Literal:
        return " or ".join(repr(a) for a in typing.get_args(tp))
    if origin in (list, tuple):
        return f"list of {_describe(typing.get_args(tp)[0])}"
    if tp is type(None):
        return "null"
    return {float: "number", dict: "map", str: "string"}.get(tp, getattr(tp, "__name__", str(tp)))


def _matches(value: Any, tp) -> bool:
    origin = typing.get_origin(tp)
    if tp is Any:
        return True
    if origin in (Union, types.UnionType):
        return any(_matches(value, a) for a in typing.get_args(tp))
    if origin is Literal:
        return any(value == a and type(value) is type(a) for a in typing.get_args(tp))
    if origin in (list, tuple):
        inner = typing.get_args(tp)[0]
        return isinstance(value, (list, tuple)) and all(_matches(v, inner) for v in value)
    if origin is dict or tp is dict:
        return isinstance(value, dict)
    if tp is type(None):
        return value is None
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if tp is str:
        return isinstance(value, str)
    raise TypeError(f"param type {tp!r} is not supported")


def _hints(schema: type) -> dict:
    return typing.get_type_hints(schema, include_extras=False)


def did_you_mean(name, names: list) -> str:
    """A hint for an unknown ``name``: "did you mean 'a' or 'b'?" (the close ones of ``names``),
    else the known names (up to 12), else how many there are."""
    close = difflib.get_close_matches(str(name), names, n=3)
    return (f"did you mean {' or '.join(map(repr, close))}?" if close
            else f"known: {', '.join(names) or 'none'}" if len(names) <= 12 else f"{len(names)} known")


def param_errors(schema: type, raw: Mapping | None, where: str = "params") -> list[str]:
    """Every problem of ``raw`` against the dataclass ``schema``, each prefixed with its place."""
    if raw is None:
        return []
    if not isinstance(raw, Mapping):
        return [f"{where}: expected a map, got {type(raw).__name__}"]
    hints = _hints(schema)
    names = [f.name for f in dataclasses.fields(schema)]
    errors = []
    for key, value in raw.items():
        if key not in hints:
            errors.append(f"{where}.{key}: unknown param ({did_you_mean(key, names)})")
        elif not _matches(value, hints[key]):
            errors.append(f"{where}.{key}: expected {_describe(hints[key])}, got {value!r}")
    return errors


def parse_params(schema: type, raw: Mapping | None, where: str = "params"):
    """An instance of the dataclass ``schema`` from ``raw``; ParamError if anything is wrong.
    Lists become tuples where the field is a tuple."""
    errors = param_errors(schema, raw, where)
    if errors:
        raise ParamError(errors)
    hints = _hints(schema)
    kw = {}
    for key, value in (raw or {}).items():
        if typing.get_origin(hints[key]) is tuple and isinstance(value, list):
            value = tuple(value)
        if hints[key] is float and isinstance(value, int):
            value = float(value)
        kw[key] = value
    try:
        return schema(**kw)
    except (TypeError, ValueError) as exc:      # a dataclass's own __post_init__ checks
        raise ParamError([f"{where}: {exc}"]) from None


def merge_schemas(name: str, *schemas: type, drop: tuple = ()) -> type:
    """One dataclass with the fields of all ``schemas`` but ``drop`` (later ones win on a shared
    name)."""
    fields, sources = {}, {}
    for s in schemas:
        hints = _hints(s)
        for f in dataclasses.fields(s):
            if f.name in drop:
                continue
            default = (dataclasses.field(default_factory=f.default_factory)
                       if f.default_factory is not dataclasses.MISSING else f.default)
            fields[f.name] = (f.name, hints[f.name], default)
            sources[f.name] = getattr(s, "__param_sources__", {}).get(f.name, s)
    merged = dataclasses.make_dataclass(name, list(fields.values()))
    merged.__param_sources__ = sources     # which dataclass declared each field (its docs)
    return merged
