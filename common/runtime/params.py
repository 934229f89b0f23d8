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
without raising (``needletrack validate`` reports them all). A value is converted strictly by
msgspec, the schema mechanism of messages too (``common.runtime.schema``): ``int``, ``float``
(finite; an int is accepted), ``bool``, ``str``, ``dict``, ``list[T]``, ``tuple[T, ...]``,
``Literal[...]``, unions (``X | None``), and constraints on the field
(``Annotated[float, msgspec.Meta(ge=0), Says("must not be negative, got {value}")]``, or the
words as the ``Meta``'s ``description``: ``common.constraints``). No
coercion of strings: ``'5'`` is not an int.
"""
from __future__ import annotations

import dataclasses
import difflib
import functools
import sys
import types
import typing
from typing import Annotated, Literal, Mapping, Union

import msgspec

from common.constraints import required_fields
from common.errors import NeedletrackError
from common.runtime.schema import Says, dec_hook


class ParamError(NeedletrackError, ValueError):
    """Params that do not match a node's schema; ``errors`` lists each with its place."""

    def __init__(self, errors: list[str]):
        super().__init__("; ".join(errors))
        self.errors = list(errors)


def describe_type(tp) -> str:
    """A field type in words, as ``needletrack describe`` prints it."""
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        return " or ".join(describe_type(a) for a in typing.get_args(tp))
    if origin is Literal:
        return " or ".join(repr(a) for a in typing.get_args(tp))
    if origin in (list, tuple):
        return f"list of {describe_type(typing.get_args(tp)[0])}"
    if tp is type(None):
        return "null"
    return {float: "number", dict: "map", str: "string"}.get(tp, getattr(tp, "__name__", str(tp)))


_FINITE = Annotated[float, msgspec.Meta(ge=-sys.float_info.max, le=sys.float_info.max)]


@functools.lru_cache(maxsize=None)
def _finite(tp):
    """``tp`` with each bare ``float`` in it finite (msgspec's float takes inf and NaN)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is float:
        return _FINITE
    if origin in (Union, types.UnionType):
        return Union[tuple(_finite(a) for a in args)]
    if origin is list:
        return list[_finite(args[0])]
    if origin is tuple and args:
        return tuple[tuple(a if a is Ellipsis else _finite(a) for a in args)]
    if origin is dict and args:
        return dict[_finite(args[0]), _finite(args[1])]
    return tp


def _convert(tp, value):
    """``(value converted to tp, None)`` or ``(None, why not)``: msgspec's strict conversion."""
    try:
        return msgspec.convert(value, _finite(tp), dec_hook=dec_hook), None
    except msgspec.ValidationError as exc:
        if typing.get_origin(tp) is Annotated and _convert(tp.__origin__, value)[1] is None:
            says = next((m for m in tp.__metadata__ if isinstance(m, Says)), None)   # the type fits, a constraint not
            words = says.text if says else next((m.description for m in tp.__metadata__       # or a Meta's words
                                                 if isinstance(m, msgspec.Meta) and m.description), None)
            detail = str(exc)
            return None, words.format(value=value) if words else f"{detail[:1].lower()}{detail[1:]}, got {value!r}"
        return None, f"expected {describe_type(_bare(tp))}, got {value!r}"


def _bare(tp):
    return tp.__origin__ if typing.get_origin(tp) is Annotated else tp


def field_types(schema: type) -> dict:
    """The field types, without their constraints (for describing them)."""
    return typing.get_type_hints(schema, include_extras=False)


def _declared(schema: type) -> dict:
    """The field types with their constraints (``Annotated``)."""
    return typing.get_type_hints(schema, include_extras=True)


def did_you_mean(name, names: list) -> str:
    """A hint for an unknown ``name``: "did you mean 'a' or 'b'?" (the close ones of ``names``),
    else the known names (up to 12), else how many there are."""
    close = difflib.get_close_matches(str(name), names, n=3)
    return (f"did you mean {' or '.join(map(repr, close))}?" if close
            else f"known: {', '.join(names) or 'none'}" if len(names) <= 12 else f"{len(names)} known")


def param_errors(schema: type, raw: Mapping | None, where: str = "params") -> list[str]:
    """Every problem of ``raw`` against the dataclass ``schema``, each prefixed with its place."""
    if raw is not None and not isinstance(raw, Mapping):
        return [f"{where}: expected a map, got {type(raw).__name__}"]
    return _converted(schema, raw or {}, where)[1]


def _converted(schema: type, raw: Mapping, where: str) -> tuple:
    """``(the converted values by name, every problem placed)``."""
    hints = _declared(schema)
    names = [f.name for f in dataclasses.fields(schema)]
    kw, errors = {}, []
    for key, value in raw.items():
        if key not in hints:
            errors.append(f"{where}.{key}: unknown param ({did_you_mean(key, names)})")
            continue
        kw[key], why = _convert(hints[key], value)
        if why:
            errors.append(f"{where}.{key}: {why}")
    errors += [f"{where}.{name}: is required ({what})" for name, what in required_fields(schema).items()
               if name not in raw]
    return kw, errors


def parse_params(schema: type, raw: Mapping | None, where: str = "params"):
    """An instance of the dataclass ``schema`` from ``raw``; ParamError if anything is wrong.
    Lists become tuples where the field is a tuple, an int a float where it is a float."""
    if raw is not None and not isinstance(raw, Mapping):
        raise ParamError([f"{where}: expected a map, got {type(raw).__name__}"])
    kw, errors = _converted(schema, raw or {}, where)
    if errors:
        raise ParamError(errors)
    try:
        return schema(**kw)
    except (TypeError, ValueError) as exc:      # a dataclass's own __post_init__ checks
        raise ParamError([f"{where}: {exc}"]) from None


def config_from(cls: type, params, rename: Mapping | None = None):
    """The library config ``cls`` (a dataclass whose fields a node's params take on, through
    ``merge_schemas``) from the typed ``params``: each field from the param of its name, or of
    ``rename[field]``."""
    rename = rename or {}
    return cls(**{f.name: getattr(params, rename.get(f.name, f.name)) for f in dataclasses.fields(cls)})


def merge_schemas(name: str, *schemas: type, drop: tuple = ()) -> type:
    """One dataclass with the fields of all ``schemas`` but ``drop`` (later ones win on a shared
    name)."""
    fields, sources = {}, {}
    for s in schemas:
        hints = _declared(s)                   # with their constraints
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
