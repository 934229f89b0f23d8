"""The one schema mechanism (msgspec): a field is declared once, as its type annotation with its
constraints on it, and converted strictly; a refusal is placed: ``Owner.field: why``.

Declaring a field (a message's, a node's params', a graph file's):

- ``NonNegative``, ``Int64``, ``Number`` (finite, within ``MAX_COORD``), ``bool``, ``str``,
  ``Literal[...]`` (one of), ``dict``, ``memoryview`` (bytes, decoded as a view of the payload);
- ``Array[5, 2]`` a numeric array of that shape (``None``: any length), finite;
  ``ArrayNaN[5, 2]`` the same with NaN allowed ("missing"); a plain list is taken as one;
- ``ByCamera[Array[5, 2]]`` a map ``{"left": array or None, "right": ...}``;
- any other constraint as msgspec ``Meta`` with the words of its refusal, ``Says``:
  ``Annotated[Number, Meta(gt=0), Says("must be positive, got {value}")]``;
- ``Optional[...]``: may be absent or null; any other field is required.

``refusal`` is the layer between msgspec's ``ValidationError`` and the placed messages: when a
message's strict conversion fails it walks the fields in their declared order and names the
first that fails, the type errors of every field before any ``Says`` (``order``) of any field.
``section_errors`` lists every failing field of a file's section (``common.runtime.graph_checks``);
node params: ``common.runtime.params``.
"""
from __future__ import annotations

import dataclasses
import functools
import typing
from typing import Annotated, Any, Literal, Optional, Union

import msgspec
import numpy as np

from common.frames import CAMERAS
from common.runtime.checks import MAX_ARRAY_ELEMENTS, MAX_COORD, MAX_INT


class Says:
    """The words of a refusal, on a constraint: ``text`` formatted with ``value`` (and ``kind``,
    the value's YAML kind: ``kind_name``); a payload that breaks several constraints is refused
    for the lowest ``order`` first (then field order). ``types``: the words are for a value of
    the wrong type too; ``missing``: the words for a required field that is absent or null (a
    file's field, ``section_errors``)."""

    def __init__(self, text: str, order: int = 2, types: bool = False, missing: Optional[str] = None):
        self.text, self.order, self.types, self.missing = text, order, types, missing

    def say(self, value) -> str:
        return self.text.format(value=value, kind=kind_name(value))

    def __repr__(self):
        return f"Says({self.text!r})"


NonNegative = Annotated[int, msgspec.Meta(ge=0, le=MAX_INT), Says("must not be negative, got {value}", order=1)]
"""``seq``, ``stamp_ns``, ``epoch``, a count: an int64 that is not negative."""

Int64 = Annotated[int, msgspec.Meta(ge=-MAX_INT, le=MAX_INT)]

Number = Annotated[float, msgspec.Meta(ge=-MAX_COORD, le=MAX_COORD)]
"""A finite number within ``MAX_COORD`` (an int is taken as a float)."""


def number(says: str, **bounds) -> type:
    """A ``Number`` within tighter ``bounds`` (msgspec ``Meta``: ``gt``, ``ge``, ``lt``, ``le``),
    refused in the words ``says``."""
    limits = {"ge": -MAX_COORD, "le": MAX_COORD}
    if "gt" in bounds:
        limits.pop("ge")
    if "lt" in bounds:
        limits.pop("le")
    return Annotated[float, msgspec.Meta(**{**limits, **bounds}), Says(says)]


Bytes = memoryview
"""Bytes: ``bytes`` when a node builds it, a read-only view of the payload when decoded (no copy)."""


# ---------------------------------------------------------------- numeric arrays

class _ArrayKind(type):
    def __instancecheck__(cls, obj):          # msgspec checks what ``dec_hook`` returns with isinstance
        return isinstance(obj, np.ndarray)


class Array(metaclass=_ArrayKind):
    """``Array[5, 2]``: a finite numeric ``np.ndarray`` of that shape (``None``: any size)."""

    SHAPE: tuple = ()
    NAN = False
    _made: dict = {}

    def __class_getitem__(cls, shape):
        shape = shape if isinstance(shape, tuple) else (shape,)
        key = (cls, shape)
        if key not in Array._made:
            name = f"{cls.__name__}[{', '.join('N' if s is None else str(s) for s in shape)}]"
            Array._made[key] = _ArrayKind(name, (cls,), {"SHAPE": shape})
        return Array._made[key]

    @classmethod
    def check(cls, value) -> np.ndarray:
        """``value`` as the array, or ValueError saying why not."""
        if isinstance(value, list):  # tolerate plain lists from other writers
            try:
                value = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                raise ValueError("expected numeric array") from None
        if not isinstance(value, np.ndarray):
            raise ValueError(f"expected array, got {type(value).__name__}")
        shape = cls.SHAPE
        if value.shape != shape and (len(value.shape) != len(shape) or any(
                s is not None and s != v for s, v in zip(shape, value.shape))):
            want = tuple("N" if s is None else s for s in shape)
            raise ValueError(f"expected shape {want}, got {value.shape}")
        if value.size > MAX_ARRAY_ELEMENTS:
            raise ValueError(f"{value.size} elements, at most {MAX_ARRAY_ELEMENTS}")
        values_error(value, cls.NAN)
        return value


class ArrayNaN(Array):
    """``ArrayNaN[5, 2]``: as ``Array``, with NaN allowed ("missing")."""

    NAN = True


def values_error(a: np.ndarray, nan_ok: bool, where: str = "") -> None:
    """ValueError unless every element is finite (NaN allowed when ``nan_ok``) and at most
    ``MAX_COORD`` in size; inf is never allowed. ``where`` prefixes the text (a key: ``.left``)."""
    lead = f"{where}: " if where else ""
    if a.dtype.kind not in "fiub":
        raise ValueError(f"{lead}expected a numeric array, got dtype {a.dtype}")
    if a.dtype.kind == "f":
        if not a.size:
            return
        top = (np.fmax if nan_ok else np.maximum).reduce(np.abs(a), axis=None)   # fmax: NaN left out
        if top > MAX_COORD or not nan_ok and top != top:
            bad = ~(np.abs(a) <= MAX_COORD)
            if nan_ok:
                bad &= ~np.isnan(a)
            raise ValueError(f"{lead}not finite, or beyond {MAX_COORD:g} ({int(bad.sum())} element(s))")
    elif a.dtype.kind in "iu" and a.size and np.abs(a.astype(np.float64)).max() > MAX_COORD:
        raise ValueError(f"{lead}element(s) beyond {MAX_COORD:g}")


class _ByCameraKind(type):
    def __instancecheck__(cls, obj):
        return isinstance(obj, dict)


class ByCamera(metaclass=_ByCameraKind):
    """``ByCamera[Array[5, 2]]``: ``{camera: array of that shape or None}`` for cameras of
    ``CAMERAS``; NaN allowed (missing)."""

    VALUE: type = Array
    _made: dict = {}

    def __class_getitem__(cls, value: type):
        if value not in ByCamera._made:
            ByCamera._made[value] = _ByCameraKind(f"ByCamera[{value.__name__}]", (cls,), {"VALUE": value})
        return ByCamera._made[value]

    @classmethod
    def check(cls, value) -> dict:
        if not isinstance(value, dict) or set(value) - set(CAMERAS):
            raise ValueError(f"expected a map with keys {'/'.join(CAMERAS)}")
        out = {}
        for k, v in value.items():
            if v is None:
                out[k] = None
                continue
            try:
                a = v if isinstance(v, np.ndarray) else np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f".{k}: expected a numeric array") from None
            if a.shape != cls.VALUE.SHAPE:
                raise ValueError(f".{k}: expected shape {cls.VALUE.SHAPE}, got {a.shape}")
            values_error(a, True, f".{k}")
            out[k] = a
        return out


def dec_hook(tp, obj):
    """msgspec's hook for the types above: their ``check``."""
    check = getattr(tp, "check", None)
    if check is None:
        raise NotImplementedError(f"no conversion to {tp!r}")
    return check(obj)


# ---------------------------------------------------------------- fields of a declaration

@dataclasses.dataclass(frozen=True)
class Field:
    """One declared field: ``name``, its full type, the type under ``Optional``/``Annotated``
    (``base``), whether it may be null (and absent, on the wire), its ``Says``, its default
    (``NODEFAULT``), and ``key``: its name in a file (``dataclasses.field(metadata={"key": ...})``;
    None: not in the file)."""

    name: str
    type: Any
    base: Any
    optional: bool
    says: Optional[Says]
    default: Any = msgspec.NODEFAULT
    key: Optional[str] = None


def _unwrap(tp):
    """``(base, optional, says)`` of a field type."""
    optional, says = False, None
    while True:
        origin = typing.get_origin(tp)
        if origin is Annotated:
            says = next((m for m in reversed(tp.__metadata__) if isinstance(m, Says)), says) or \
                next((Says(m.description) for m in tp.__metadata__          # common.constraints' words
                      if isinstance(m, msgspec.Meta) and m.description), None)
            tp = tp.__origin__
        elif origin is Union and type(None) in typing.get_args(tp):
            optional = True
            rest = [a for a in typing.get_args(tp) if a is not type(None)]
            tp = rest[0] if len(rest) == 1 else Union[tuple(rest)]
        else:
            return tp, optional, says


@functools.lru_cache(maxsize=None)
def fields_of(cls) -> tuple:
    """The ``Field``s of a dataclass (a message, a file's section), in declared order."""
    hints = typing.get_type_hints(cls, include_extras=True)
    out = []
    for f in dataclasses.fields(cls):
        base, optional, says = _unwrap(hints[f.name])
        default = (f.default if f.default is not dataclasses.MISSING else
                   f.default_factory if f.default_factory is not dataclasses.MISSING else msgspec.NODEFAULT)
        out.append(Field(f.name, hints[f.name], base, optional, says, default, f.metadata.get("key", f.name)))
    return tuple(out)


def wire_struct(cls) -> type:
    """A msgspec Struct with ``cls``'s fields as they travel: unknown fields refused, the
    ``Optional`` ones absent as None, every other one required (a Python default is not a wire
    default)."""
    spec = [(f.name, f.type, None) if f.optional else (f.name, f.type) for f in fields_of(cls)]
    return msgspec.defstruct(cls.__name__, spec, kw_only=True, forbid_unknown_fields=True)


# ---------------------------------------------------------------- refusals, placed

def _type_name(value) -> str:
    return type(value).__name__


def kind_name(v) -> str:
    """A value's kind in a YAML file's words: map, list, string, int, number, bool, null."""
    return {dict: "map", list: "list", str: "string", int: "int", float: "number", bool: "bool",
            type(None): "null"}.get(type(v), type(v).__name__)


def field_refusal(f: Field, value) -> Optional[tuple]:
    """``(order, why)`` if ``value`` is not a valid ``f``, else None; order 0: a type error."""
    if value is None:
        return None if f.optional else (0, "required, got null")
    base = f.base
    check = getattr(base, "check", None)
    if check is not None:
        try:
            check(value)
            return None
        except ValueError as exc:
            return 0, str(exc)
    origin = typing.get_origin(base) or base
    if base is int and (isinstance(value, bool) or not isinstance(value, int)):
        return 0, f"expected int, got {_type_name(value)}"
    if base is float and (isinstance(value, bool) or not isinstance(value, (int, float))):
        return 0, f"expected number, got {_type_name(value)}"
    if origin is Literal and not isinstance(value, str):
        return 0, f"expected string, got {_type_name(value)}"
    want = _KINDS.get(origin)
    if want is not None and not isinstance(value, want[0]):
        return 0, f"expected {want[1]}, got {_type_name(value)}"
    try:
        msgspec.convert(value, f.type, dec_hook=dec_hook)
        return None
    except msgspec.ValidationError as exc:
        detail = str(exc)
    said = None if f.says is None else (f.says.order, f.says.say(value))
    if base is int and not -MAX_INT <= value <= MAX_INT:
        return 0, f"out of the int64 range, got {value}"
    if base is float:
        value = float(value)
        if not abs(value) <= MAX_COORD:          # NaN and inf fail this too
            return 0, f"not finite, or beyond {MAX_COORD:g}: got {value}"
        said = None if said is None else (said[0], f.says.say(value))
    if origin is Literal:
        return 0, f"must be one of {typing.get_args(base)}, got {value!r}"
    return said or (0, detail)


_KINDS = {bool: (bool, "bool"), str: (str, "string"), dict: (dict, "map"), list: (list, "list"),
          memoryview: ((bytes, bytearray, memoryview), "bytes"), bytes: ((bytes, bytearray, memoryview), "bytes")}


def refusal(owner: str, fields: tuple, body) -> str:
    """The placed message for a message's ``body``, which a strict conversion refused: the
    unknown field first, then the first field in declared order that is missing (only the
    ``Optional`` ones may be) or of the wrong type, then the first that breaks a ``Says``
    (lowest order)."""
    if not isinstance(body, dict):
        return f"{owner}: body is not a map"
    known = {f.name for f in fields}
    unknown = [k for k in body if k not in known]
    if unknown:
        return f"{owner}.{min(unknown, key=str)}: unknown field"
    later = None
    for f in fields:
        if f.name not in body:
            if f.optional:
                continue
            return f"{owner}.{f.name}: missing"
        got = field_refusal(f, body[f.name])
        if got is None:
            continue
        order, why = got
        placed = f"{owner}.{f.name}{why}" if why.startswith(".") else f"{owner}.{f.name}: {why}"
        if order == 0:
            return placed
        if later is None or order < later[0]:
            later = (order, placed)
    return later[1] if later else f"{owner}: invalid"


def file_keys(cls) -> list:
    """The keys a file's section may hold: ``cls``'s fields that are in the file, sorted."""
    return sorted(f.key for f in fields_of(cls) if f.key is not None)


def unknown_key_errors(where: str, cls, data: dict) -> list:
    """An error for each key of the file section ``data`` that ``cls`` does not declare."""
    keys = file_keys(cls)
    return [f"{where}{k}: unknown key (allowed: {', '.join(keys)})" for k in data if k not in keys]


def section_errors(where: str, cls, data: dict, keys: Optional[tuple] = None) -> list:
    """Every problem of the file section ``data`` (a map) against the dataclass ``cls``: each
    field of ``keys`` (default: all) in declared order that is missing (``Says.missing``) or
    refused (a ``Says(types=True)``'s words, else ``field_refusal``'s). A field of a dataclass
    type (a nested section) is only checked to be a map here. ``where`` prefixes each
    (``"zenoh."``, ``"nodes[2]."``)."""
    fields = [f for f in fields_of(cls) if f.key is not None]
    errs = []
    for f in fields:
        if keys is not None and f.key not in keys:
            continue
        value = data.get(f.key)
        if f.says is not None and f.says.missing is not None and value is None:
            errs.append(f"{where}{f.key}: {f.says.missing}")
            continue
        if f.key not in data or value is None and f.optional:
            continue
        if dataclasses.is_dataclass(f.base):
            why = None if isinstance(value, dict) else (0, f"expected a map, got {kind_name(value)}")
        else:
            why = field_refusal(f, value)
        if why is not None:
            errs.append(f"{where}{f.key}: {f.says.say(value) if f.says is not None and f.says.types else why[1]}")
    return errs
