"""A reader of the .NET Remoting Binary Format (MS-NRBF), the format of Elekta Unity's cine ``.bin`` files.

The format is Microsoft's published specification [MS-NRBF] (".NET Remoting: Binary Format Data Structure"):
a stream of records, each starting with a one-byte record type, that together serialise one object graph
(classes with named members, strings, arrays of primitives or objects, references between them). This module
reads such a stream into plain Python: a class becomes a :class:`NrbfObject` (its .NET class name and a dict of
its members), a string a ``str``, an array of primitives a numpy array, any other array a list, and every
reference is resolved to the object it names. It writes nothing and runs no code from the stream (no type is
instantiated): a ``.bin`` is data only here.

Only the records a serialised object graph uses are read; a method call or return record (remoting messages)
is refused with :class:`~warpmpm.errors.InputError`, as is a truncated or malformed stream.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError

__all__ = ["NrbfObject", "read_nrbf"]

# PrimitiveTypeEnum -> (struct format, numpy dtype); 3 (Char), 5 (Decimal) and 18 (String) are read apart
_PRIMITIVE = {
    1: ("<?", "?"), 2: ("<B", "u1"), 6: ("<d", "<f8"), 7: ("<h", "<i2"), 8: ("<i", "<i4"), 9: ("<q", "<i8"),
    10: ("<b", "i1"), 11: ("<f", "<f4"), 12: ("<q", "<i8"), 13: ("<Q", "<u8"), 14: ("<H", "<u2"),
    15: ("<I", "<u4"), 16: ("<Q", "<u8"),
}


@dataclass
class NrbfObject:
    """One serialised .NET object: its class name and its members by name (resolved)."""

    class_name: str
    members: dict = field(default_factory=dict)

    def __getitem__(self, name):
        return self.members[name]

    def get(self, name, default=None):
        return self.members.get(name, default)

    def field(self, name: str):
        """A member by its property name: ``field("Origin")`` finds the compiler's ``<Origin>k__BackingField``."""
        for key in (name, f"<{name}>k__BackingField", f"_{name}", f"m_{name}"):
            if key in self.members:
                return self.members[key]
        raise KeyError(f"{self.class_name} has no member {name!r} (members: {', '.join(self.members)})")


class _Ref:
    __slots__ = ("id",)

    def __init__(self, object_id: int):
        self.id = object_id


class _Nulls:
    __slots__ = ("count",)

    def __init__(self, count: int):
        self.count = count


class _Reader:
    def __init__(self, data: bytes, source: str):
        self.data = data
        self.pos = 0
        self.source = source
        self.objects: dict[int, object] = {}
        self.classes: dict[int, tuple] = {}  # object id -> (name, member names, member types)

    def fail(self, what: str):
        raise InputError(f"{self.source} is not a readable .NET binary (MS-NRBF) stream: {what} at byte {self.pos}")

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            self.fail(f"it ends early (wanted {n} bytes)")
        b = self.data[self.pos:self.pos + n]
        self.pos += n
        return b

    def unpack(self, fmt: str):
        return struct.unpack(fmt, self.take(struct.calcsize(fmt)))[0]

    def i32(self) -> int:
        return self.unpack("<i")

    def byte(self) -> int:
        return self.take(1)[0]

    def string(self) -> str:
        length, shift = 0, 0
        for _ in range(5):  # 7-bit encoded length, at most 5 bytes
            b = self.byte()
            length |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                break
        else:
            self.fail("a string length longer than 5 bytes")
        try:
            return self.take(length).decode("utf-8")
        except UnicodeDecodeError:
            self.fail("a string that is not UTF-8")

    def primitive(self, kind: int):
        if kind in _PRIMITIVE:
            return self.unpack(_PRIMITIVE[kind][0])
        if kind == 3:  # Char: one UTF-8 character
            first = self.data[self.pos] if self.pos < len(self.data) else 0
            n = 1 if first < 0x80 else 2 if first < 0xE0 else 3 if first < 0xF0 else 4
            return self.take(n).decode("utf-8", errors="replace")
        if kind in (5, 18):  # Decimal (as its string), String
            return self.string()
        if kind == 17:
            return None
        self.fail(f"an unknown primitive type {kind}")

    def class_info(self):
        object_id = self.i32()
        name = self.string()
        count = self.i32()
        if not 0 <= count < 1 << 16:
            self.fail(f"a class with {count} members")
        return object_id, name, [self.string() for _ in range(count)]

    def member_types(self, count: int):
        kinds = list(self.take(count))
        extra = []
        for k in kinds:
            if k in (0, 7):
                extra.append(self.byte())
            elif k == 3:
                extra.append(self.string())
            elif k == 4:
                extra.append((self.string(), self.i32()))
            elif k in (1, 2, 5, 6):
                extra.append(None)
            else:
                self.fail(f"an unknown member type {k}")
        return list(zip(kinds, extra))

    def members(self, object_id, name, names, types):
        obj = NrbfObject(name)
        self.objects[object_id] = obj
        values = []
        while len(values) < len(names):
            kind = types[len(values)] if types is not None else None
            if kind is not None and kind[0] == 0:
                values.append(self.primitive(kind[1]))
                continue
            v = self.record()
            if isinstance(v, _Nulls):
                values.extend([None] * v.count)
            else:
                values.append(v)
        if len(values) != len(names):
            self.fail(f"{name} has more null members than members")
        obj.members = dict(zip(names, values))
        return obj

    def elements(self, count: int, kind):
        if kind is not None and kind[0] == 0:
            return self.primitive_array(count, kind[1])
        out = []
        while len(out) < count:
            v = self.record()
            out.extend([None] * v.count if isinstance(v, _Nulls) else [v])
        return out[:count]

    def primitive_array(self, count: int, kind: int):
        if count < 0:
            self.fail(f"an array of length {count}")
        if kind in _PRIMITIVE:
            dtype = np.dtype(_PRIMITIVE[kind][1])
            return np.frombuffer(self.take(count * dtype.itemsize), dtype=dtype).copy()
        return [self.primitive(kind) for _ in range(count)]

    def record(self):
        rtype = self.byte()
        if rtype == 1:  # ClassWithId: reuses an earlier class's metadata
            object_id, meta = self.i32(), self.i32()
            if meta not in self.classes:
                self.fail(f"a reference to undeclared class metadata {meta}")
            name, names, types = self.classes[meta]
            return self.members(object_id, name, names, types)
        if rtype in (2, 3, 4, 5):  # (System)ClassWithMembers(AndTypes)
            object_id, name, names = self.class_info()
            types = self.member_types(len(names)) if rtype in (4, 5) else None
            if rtype in (3, 5):
                self.i32()  # library id
            self.classes[object_id] = (name, names, types)
            return self.members(object_id, name, names, types)
        if rtype == 6:  # BinaryObjectString
            object_id = self.i32()
            s = self.string()
            self.objects[object_id] = s
            return s
        if rtype == 7:  # BinaryArray
            object_id, array_type, rank = self.i32(), self.byte(), self.i32()
            if not 1 <= rank <= 32:
                self.fail(f"an array of rank {rank}")
            lengths = [self.i32() for _ in range(rank)]
            if array_type in (3, 4, 5):
                [self.i32() for _ in range(rank)]  # lower bounds
            kind = self.member_types(1)[0]
            count = int(np.prod(lengths))
            value = self.elements(count, kind)
            if isinstance(value, np.ndarray) and rank > 1:
                value = value.reshape(lengths)
            self.objects[object_id] = value
            return value
        if rtype == 8:  # MemberPrimitiveTyped
            return self.primitive(self.byte())
        if rtype == 9:  # MemberReference
            return _Ref(self.i32())
        if rtype == 10:
            return None
        if rtype == 12:  # BinaryLibrary: a declaration, then the record it precedes
            self.i32()
            self.string()
            return self.record()
        if rtype == 13:
            return _Nulls(self.byte())
        if rtype == 14:
            return _Nulls(self.i32())
        if rtype == 15:  # ArraySinglePrimitive
            object_id, count, kind = self.i32(), self.i32(), self.byte()
            value = self.primitive_array(count, kind)
            self.objects[object_id] = value
            return value
        if rtype in (16, 17):  # ArraySingleObject, ArraySingleString
            object_id, count = self.i32(), self.i32()
            value = self.elements(count, None)
            self.objects[object_id] = value
            return value
        self.pos -= 1
        self.fail(f"record type {rtype} (a remoting message or not an NRBF stream)")


def _resolve(value, objects, seen):
    if isinstance(value, _Ref):
        if value.id not in objects:
            raise InputError(f"a .NET binary stream refers to object {value.id}, which it never defines")
        value = objects[value.id]
    if id(value) in seen:
        return value
    if isinstance(value, NrbfObject):
        seen.add(id(value))
        for k, v in value.members.items():
            value.members[k] = _resolve(v, objects, seen)
    elif isinstance(value, list):
        seen.add(id(value))
        for i, v in enumerate(value):
            value[i] = _resolve(v, objects, seen)
    return value


def read_nrbf(data: bytes, source: str = "the stream"):
    """The root object of an MS-NRBF stream (``data``: the whole file), every reference resolved.

    Raises :class:`InputError` naming ``source`` when the stream is not NRBF, is truncated, or is malformed.
    """
    r = _Reader(bytes(data), source)
    if len(data) < 17 or r.byte() != 0:
        r.pos = 0
        r.fail("no serialisation header")
    root_id = r.i32()
    r.i32()
    major, minor = r.i32(), r.i32()
    if (major, minor) != (1, 0):
        r.fail(f"format version {major}.{minor} (1.0 expected)")
    while True:
        if r.pos >= len(r.data):
            r.fail("no end-of-message record")
        if r.data[r.pos] == 11:  # MessageEnd
            break
        value = r.record()
        if isinstance(value, (_Ref, _Nulls)) or value is None:
            r.fail("a reference or null outside any object")
    if root_id not in r.objects:
        r.fail(f"no root object (id {root_id})")
    return _resolve(r.objects[root_id], r.objects, set())
