"""The wire form of every message: what each msgpack map must hold, as msgspec Structs.

:func:`agent.wire.decode` reads a message's bytes straight into its form, so that the map's shape, the fields'
types, the lengths of lists and maps and the bounds of integers are checked by msgspec's compiled decoder, in
one pass, instead of field by field in Python (every sensor decodes every exchange payload of its neighbours,
the recorder every message of a run). What a form cannot say — that an array's bytes fill its shape and are
finite, that a tick's neighbour lists are sorted and within ``n``, that floats are finite — :mod:`agent.wire`
checks after it, on the decoded values.

A form names its message's fields as they travel (``agent/wire.py`` has the key table and the message classes).
Arrays travel as :class:`Arr`: ``{"s": shape, "d": little-endian float64 bytes}``. Unknown fields of a message
are ignored (a newer sender may add optional ones); an array's map must hold exactly ``s`` and ``d``.
:func:`reason` turns msgspec's complaint into the stable label a bus counts drops by.
"""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta, Struct

MAX_MESSAGE_BYTES = 1 << 20      #: larger payloads are rejected before unpacking
MAX_ARRAY_ELEMENTS = 1 << 16     #: per array
MAX_LIST_LEN = 4096              #: per list field (neighbour lists, per-node vectors)
MAX_PAYLOAD_ENTRIES = 32         #: entries of an exchange payload
MAX_ROUND = 1000                 #: an exchange payload's round
MAX_WHOLE = 2**53                #: the largest integer a message may carry (exact as a float too)

SensorId = Annotated[int, Meta(ge=0, le=MAX_LIST_LEN)]
Count = Annotated[int, Meta(ge=0, le=MAX_WHOLE)]
Name = Annotated[str, Meta(max_length=64)]
Floats = Annotated[list[float], Meta(max_length=MAX_LIST_LEN)]


class Arr(Struct, forbid_unknown_fields=True):
    """An array: its shape (one or two dimensions) and its data, ``prod(shape)`` little-endian float64."""

    s: Annotated[list[Annotated[int, Meta(ge=0, le=MAX_ARRAY_ELEMENTS)]], Meta(min_length=1, max_length=2)]
    d: bytes


Arrays = Annotated[dict[Name, Arr], Meta(max_length=MAX_PAYLOAD_ENTRIES)]


class Form(Struct, kw_only=True):
    """Every message: its type, its sender's id within its role, its tick."""

    type: str
    src: SensorId
    k: Count


class TickForm(Form):
    t: float
    n: SensorId
    links: Annotated[list[Annotated[list[SensorId], Meta(max_length=MAX_LIST_LEN)]], Meta(max_length=MAX_LIST_LEN)]
    weights: Annotated[list[Floats], Meta(max_length=MAX_LIST_LEN)]
    b: Floats
    delta_max: SensorId
    alive: Annotated[list[bool], Meta(max_length=MAX_LIST_LEN)]
    positions: Arr
    period: float = 0.0


class TruthForm(Form):
    t: float
    x: Arr


class MeasForm(Form):
    t: float
    y: Arr
    b: float
    pos: Arr
    v: Arr | None = None


class XchgForm(Form):
    r: Annotated[int, Meta(ge=0, le=MAX_ROUND)]
    payload: Arrays


class XchgHeader(Form):
    """An exchange payload's header alone (its arrays unread): what may still be said of one whose arrays
    did not validate."""

    r: Annotated[int, Meta(ge=0, le=MAX_ROUND)]


class ViaXchgForm(XchgForm):
    to: Annotated[list[SensorId], Meta(max_length=MAX_LIST_LEN)]


class RoundsForm(Form):
    payloads: Annotated[list[Arrays], Meta(max_length=MAX_ROUND)]


class EstimateForm(Form):
    x: Arr
    x_next: Arr
    P: Arr | None = None
    name: Name = ""
    aux: Arrays = {}


class StateForm(Form):
    pos: Arr
    vel: Arr
    w: Arr | None = None


#: a control's argument: a flag, a whole number, a number, a text or a list of numbers
Arg = (None | bool | Annotated[int, Meta(ge=-MAX_WHOLE, le=MAX_WHOLE)] | float | str
       | Annotated[list[int | float], Meta(max_length=MAX_LIST_LEN)])


class ControlForm(Form):
    verb: Name
    args: Annotated[dict[Name, Arg], Meta(max_length=64)] = {}


class EndForm(Form):
    reason: Name = "done"


class _TypeOnly(Struct):
    type: str


_TYPE_ONLY = msgspec.msgpack.Decoder(_TypeOnly)


def type_of(data: bytes) -> str | None:
    """The ``type`` a message's bytes claim, or None when they do not say (or are no message at all)."""
    try:
        return _TYPE_ONLY.decode(data).type
    except msgspec.MsgspecError:
        return None


def reason(err: msgspec.ValidationError, array_fields: frozenset[str]) -> str:
    """The drop label of a form's complaint: ``bad_encoding`` when the message is not a map, ``bad_shape`` /
    ``bad_array`` when the fault is inside one of ``array_fields`` (an array, or an entry of a map of
    arrays: its shape, or the rest of it), else ``bad_field``."""
    text = str(err)
    path = text.rpartition(" - at `")[2].rstrip("`") if " - at `" in text else "$"
    if path == "$":
        if text.startswith("Expected `object`"):
            return "bad_encoding"
        missing = text.partition("missing required field `")[2].rstrip("`")
        return "bad_array" if missing in array_fields else "bad_field"
    head = path[2:].split(".", 1)[0].split("[", 1)[0]
    if head not in array_fields or path == f"$.{head}" and head in ("payload", "aux"):
        return "bad_field"     # (a map of arrays that is not one, or has too many entries, is a bad field)
    rest = path[2 + len(head):].lstrip(".")
    return "bad_shape" if rest.startswith("s") or ".s" in rest else "bad_array"
