"""``sensor_msgs/PointCloud2`` and ``nav_msgs/Odometry`` read straight from their serialised
(CDR) bytes.

rclpy's deserialisation builds a Python message object, with a ``PointField`` object per
field (an object per vector and quaternion for Odometry), for every message; reading a bag
of twenty thousand measurement messages spent more time there than in the estimation.
:func:`parse_cloud` reads the few numbers and strings a measurement message has with
``struct`` and leaves the point bytes as they are, and it remembers the field lists it has
read, so that a stream of messages from one station costs a byte comparison each;
:func:`parse_odometry` takes the 85 numbers of a state as one numpy view.

The results, :class:`WireCloud` and :class:`WireOdometry`, have the attribute names of the
messages that the decoders (:func:`~orbit_tracking.ros.conversions.cloud_to_measurements`,
``odometry_to_*``) read, so the checks of the contract stay in one place. Only
little-endian CDR (what every ROS 2 platform we meet writes) is read here; anything else,
and anything this parser finds malformed, is ``None``. :func:`read_message` is what a
reader of serialised messages calls: the direct reader where there is one, rclpy where
there is none or where it declines (rclpy then decides whether the bytes are a message at
all).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, NamedTuple

import numpy as np
from rclpy.serialization import deserialize_message

__all__ = [
    'WireCloud',
    'WireField',
    'WireHeader',
    'WireOdometry',
    'WireStamp',
    'cloud_cdr',
    'parse_cloud',
    'parse_odometry',
    'read_message',
]

_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iI')
_TWO_U32 = struct.Struct('<II')
_THREE_U32 = struct.Struct('<III')
_CDR_LE = (b'\x00\x01', b'\x00\x03')  # CDR and PL_CDR, little-endian
_MAX_FIELDS = 1024


class WireStamp(NamedTuple):
    sec: int
    nanosec: int


class WireHeader(NamedTuple):
    stamp: WireStamp
    frame_id: str


class WireField(NamedTuple):
    name: str
    offset: int
    datatype: int
    count: int


@dataclass(frozen=True, slots=True)
class WireCloud:
    """The content of one serialised ``PointCloud2``; ``data`` is the point bytes."""

    header: WireHeader
    height: int
    width: int
    fields: tuple[WireField, ...]
    is_bigendian: bool
    point_step: int
    row_step: int
    data: bytes
    is_dense: bool


class _Reader:
    """A cursor over CDR bytes; positions are aligned relative to the payload (after the
    4-byte encapsulation header). Every read past the end raises IndexError."""

    __slots__ = ('buf', 'pos')

    def __init__(self, buf: bytes, pos: int) -> None:
        self.buf = buf
        self.pos = pos

    def align(self, size: int) -> None:
        self.pos += -(self.pos - 4) % size

    def u32(self) -> int:
        self.align(4)
        if self.pos + 4 > len(self.buf):
            raise IndexError('past the end')
        (v,) = _U32.unpack_from(self.buf, self.pos)
        self.pos += 4
        return int(v)

    def u8(self) -> int:
        if self.pos >= len(self.buf):
            raise IndexError('past the end')
        v = self.buf[self.pos]
        self.pos += 1
        return v

    def string(self) -> str:
        n = self.u32()
        end = self.pos + n
        if n == 0 or end > len(self.buf) or self.buf[end - 1] != 0:
            raise IndexError('bad string')
        s = self.buf[self.pos : end - 1].decode('utf-8')
        self.pos = end
        return s


_layouts: dict[bytes, tuple[WireField, ...]] = {}
"""Field lists by their serialised bytes (with the alignment phase they were read at)."""


def _fields(r: _Reader) -> tuple[WireField, ...]:
    start = r.pos
    n = r.u32()
    if n > _MAX_FIELDS:
        raise IndexError('too many fields')
    # A field list seen before: compare its bytes and skip the parse.
    for key, fields in _layouts.items():
        if key[0] == (start - 4) % 4 and r.buf.startswith(key[1:], start):
            r.pos = start + len(key) - 1
            return fields
    out = []
    for _ in range(n):
        name = r.string()
        offset = r.u32()
        datatype = r.u8()
        count = r.u32()
        out.append(WireField(name, offset, datatype, count))
    fields = tuple(out)
    if len(_layouts) < 256:
        _layouts[bytes([(start - 4) % 4]) + r.buf[start : r.pos]] = fields
    return fields


def parse_cloud(raw: bytes) -> WireCloud | None:
    """The ``PointCloud2`` in ``raw`` (a serialised message as a bag or a raw subscription
    holds it), or None when it is not little-endian CDR or not well formed."""
    if raw[:2] not in _CDR_LE:
        return None
    try:
        r = _Reader(raw, 4)
        if len(raw) < 12:
            return None
        sec, nanosec = _STAMP.unpack_from(raw, 4)
        r.pos = 12
        frame_id = r.string()
        r.align(4)
        height, width = _TWO_U32.unpack_from(raw, r.pos)
        r.pos += 8
        fields = _fields(r)
        is_bigendian = r.u8()
        r.align(4)
        point_step, row_step, n = _THREE_U32.unpack_from(raw, r.pos)
        r.pos += 12
        data = raw[r.pos : r.pos + n]
        if len(data) != n:
            return None
        r.pos += n
        is_dense = r.u8()
    except (IndexError, UnicodeDecodeError, struct.error):
        return None
    if is_bigendian > 1 or is_dense > 1:
        return None
    return WireCloud(
        header=WireHeader(WireStamp(int(sec), int(nanosec)), frame_id),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=bool(is_bigendian),
        point_step=point_step,
        row_step=row_step,
        data=data,
        is_dense=bool(is_dense),
    )


_ODOMETRY_DOUBLES = 7 + 36 + 6 + 36
"""Pose (position, orientation), its covariance, twist (linear, angular), its covariance."""


class _Xyz(NamedTuple):
    x: float
    y: float
    z: float


class _Xyzw(NamedTuple):
    x: float
    y: float
    z: float
    w: float


@dataclass(frozen=True, slots=True)
class WireOdometry:
    """The content of one serialised ``nav_msgs/Odometry``: ``pose.pose.position``,
    ``pose.pose.orientation``, ``pose.covariance``, ``twist.twist.linear``,
    ``twist.twist.angular``, ``twist.covariance`` as in the message (covariances as arrays
    of 36)."""

    header: WireHeader
    child_frame_id: str
    pose: SimpleNamespace
    twist: SimpleNamespace


def parse_odometry(raw: bytes) -> WireOdometry | None:
    """The ``Odometry`` in ``raw``, or None when it is not little-endian CDR or not well
    formed (see :func:`parse_cloud`)."""
    if raw[:2] not in _CDR_LE or len(raw) < 12:
        return None
    try:
        r = _Reader(raw, 4)
        sec, nanosec = _STAMP.unpack_from(raw, 4)
        r.pos = 12
        frame_id = r.string()
        child = r.string()
    except (IndexError, UnicodeDecodeError):
        return None
    r.align(8)
    start = r.pos
    if start + 8 * _ODOMETRY_DOUBLES > len(raw):
        return None
    d = np.frombuffer(raw, '<f8', _ODOMETRY_DOUBLES, start)
    p, q, t = d[0:3].tolist(), d[3:7].tolist(), d[43:49].tolist()
    pose = SimpleNamespace(
        pose=SimpleNamespace(position=_Xyz(*p), orientation=_Xyzw(*q)), covariance=d[7:43]
    )
    twist = SimpleNamespace(
        twist=SimpleNamespace(linear=_Xyz(*t[:3]), angular=_Xyz(*t[3:])), covariance=d[49:85]
    )
    return WireOdometry(
        WireHeader(WireStamp(int(sec), int(nanosec)), frame_id), child, pose, twist
    )


def _string_cdr(out: bytearray, text: str) -> None:
    out += b'\0' * (-(len(out) - 4) % 4)
    b = text.encode('utf-8') + b'\0'
    out += _U32.pack(len(b)) + b


_cloud_middles: dict[tuple[str, np.dtype, int], bytes] = {}


def cloud_cdr(arr: np.ndarray, stamp_ns: int, frame_id: str, datatypes: Sequence[int]) -> bytes:
    """The serialised ``PointCloud2`` (little-endian CDR, as rclpy's ``serialize_message``
    writes it) of the structured array ``arr``: one row, dense, a field per dtype field at its
    offset with the ``PointField`` datatype ``datatypes[i]`` and count 1, stamped
    ``stamp_ns``. Everything between the stamp and the point bytes is kept per (station,
    layout, width), so a stream of messages costs a join."""
    n = int(arr.shape[0])
    key = (frame_id, arr.dtype, n)
    middle = _cloud_middles.get(key)
    if middle is None:
        out = bytearray(12)
        _string_cdr(out, frame_id)
        out += b'\0' * (-(len(out) - 4) % 4)
        out += _TWO_U32.pack(1, n)
        names = arr.dtype.names or ()
        out += _U32.pack(len(names))
        for name, datatype in zip(names, datatypes, strict=True):
            _string_cdr(out, name)
            out += b'\0' * (-(len(out) - 4) % 4)
            out += _U32.pack(int(arr.dtype.fields[name][1])) + bytes([datatype])
            out += b'\0' * (-(len(out) - 4) % 4)
            out += _U32.pack(1)
        out += b'\0'  # is_bigendian
        out += b'\0' * (-(len(out) - 4) % 4)
        step = arr.dtype.itemsize
        out += _THREE_U32.pack(step, step * n, step * n)
        middle = bytes(out[12:])
        if len(_cloud_middles) >= 1024:
            _cloud_middles.clear()
        _cloud_middles[key] = middle
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return b''.join(
        (b'\x00\x01\x00\x00', _STAMP.pack(sec, nanosec), middle, arr.tobytes(), b'\x01')
    )


_READERS = {
    'sensor_msgs/msg/PointCloud2': parse_cloud,
    'nav_msgs/msg/Odometry': parse_odometry,
}


def read_message(raw: bytes, msgtype: str, cls: type | None = None) -> Any:
    """The message of type ``msgtype`` (``pkg/msg/Name``) serialised in ``raw``: a
    :class:`WireCloud` or :class:`WireOdometry` when the direct reader can read it, else
    rclpy's message (its class ``cls``, or looked up).

    Raises
    ------
    ValueError
        Not a message of that type (rclpy's error, in one line).
    """
    raw = bytes(raw)
    reader = _READERS.get(msgtype)
    msg = reader(raw) if reader is not None else None
    if msg is not None:
        return msg
    if cls is None:
        import importlib

        pkg, _, name = msgtype.split('/')
        cls = getattr(importlib.import_module(f'{pkg}.msg'), name)
    try:
        return deserialize_message(raw, cls)
    except Exception as exc:  # whatever rclpy raises for bytes that are no message
        raise ValueError(f'not a {msgtype}: {exc}') from exc
