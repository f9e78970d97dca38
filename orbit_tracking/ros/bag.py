"""rosbag2 files: written and read with ``rosbags``; message bytes are CDR produced and
parsed by ``rclpy.serialization``, so a bag written here is read by ``ros2 bag play`` and
a bag recorded by ``ros2 bag record`` is read here.

Every read goes through one opening step (:func:`bag_folder`, :func:`bag_metadata`, the
reader of :func:`bag_topics`, :func:`read_bag` and :func:`scan_bag`): a path that is not a
readable bag, a broken ``metadata.yaml``, a missing or truncated storage file, or a message
that cannot be read half way through, raises :class:`BagError` with one line naming the bag
and what is wrong (the command line prints it and exits 2).
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Collection, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import yaml
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from orbit_tracking.core.errors import OrbitTrackingError

__all__ = [
    'BagError',
    'BagMessage',
    'BagWriter',
    'bag_custom_data',
    'bag_folder',
    'bag_metadata',
    'bag_topics',
    'message_class',
    'msgtype_of',
    'read_bag',
    'scan_bag',
]

_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
_STORAGE = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}


def msgtype_of(msg: Any) -> str:
    """``pkg/msg/Name`` of an rclpy message instance."""
    pkg = type(msg).__module__.split('.')[0]
    return f'{pkg}/msg/{type(msg).__name__}'


def message_class(msgtype: str) -> type:
    """rclpy message class of ``pkg/msg/Name``."""
    pkg, kind, name = msgtype.split('/')
    return getattr(importlib.import_module(f'{pkg}.{kind}'), name)  # type: ignore[no-any-return]


def _qos(profile: QoSProfile) -> Qos:
    zero = QosTime(sec=0, nsec=0)
    return Qos(
        history=QosHistory(int(profile.history)),
        depth=int(profile.depth),
        reliability=QosReliability(int(profile.reliability)),
        durability=QosDurability(int(profile.durability)),
        deadline=zero,
        lifespan=zero,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=zero,
        avoid_ros_namespace_conventions=False,
    )


class BagWriter:
    """Write rclpy messages (or already serialised CDR bytes) to a new rosbag2 folder.

    Parameters
    ----------
    path : path-like
        Bag folder to create (must not exist).
    storage : {'mcap', 'sqlite3'}
    """

    def __init__(self, path: str | Path, storage: str = 'mcap') -> None:
        if storage not in _STORAGE:
            raise ValueError(f'storage must be one of {sorted(_STORAGE)}; got {storage!r}')
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f'bag folder {self.path} exists already; choose another --out')
        self._writer = Writer(self.path, version=9, storage_plugin=_STORAGE[storage])
        self._writer.open()
        self._connections: dict[str, Any] = {}
        self.count = 0

    def _connection(self, topic: str, msgtype: str, qos: QoSProfile | None) -> Any:
        conn = self._connections.get(topic)
        if conn is None:
            profiles = [_qos(qos)] if qos is not None else []
            conn = self._writer.add_connection(
                topic, msgtype, typestore=_TYPESTORE, offered_qos_profiles=profiles
            )
            self._connections[topic] = conn
        elif conn.msgtype != msgtype:
            raise ValueError(f'topic {topic} has type {conn.msgtype}, cannot write {msgtype}')
        return conn

    def write(self, topic: str, msg: Any, t_ns: int, qos: QoSProfile | None = None) -> None:
        """Write one rclpy message at log time ``t_ns``."""
        conn = self._connection(topic, msgtype_of(msg), qos)
        self._writer.write(conn, int(t_ns), serialize_message(msg))
        self.count += 1

    def write_raw(
        self, topic: str, msgtype: str, data: bytes, t_ns: int, qos: QoSProfile | None = None
    ) -> None:
        """Write already serialised CDR bytes."""
        self._writer.write(self._connection(topic, msgtype, qos), int(t_ns), data)
        self.count += 1

    def set_custom_data(self, key: str, value: str) -> None:
        """Store a string in the bag's metadata (rosbag2 ``custom_data``)."""
        self._writer.set_custom_data(key, value)

    def close(self) -> None:
        self._writer.close()

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


@dataclass(frozen=True)
class BagMessage:
    """One message read back from a bag."""

    topic: str
    msgtype: str
    log_time_ns: int
    msg: Any


class BagError(OrbitTrackingError):
    """A path that is not a readable rosbag2: the message is one line naming the bag and
    what is wrong with it."""


_STORAGE_SUFFIXES = ('.mcap', '.db3')


def _one_line(exc: BaseException) -> str:
    text = ' '.join(str(exc).split()).rstrip('.')
    return text or type(exc).__name__


def _storage_files(info: dict[str, Any]) -> list[str]:
    files = info.get('relative_file_paths') or []
    if not isinstance(files, list):
        return []
    return [Path(str(f)).name for f in files]


def bag_folder(path: str | Path) -> Path:
    """The rosbag2 folder ``path`` stands for, checked to exist and to hold a
    ``metadata.yaml``.

    A storage file (``.mcap``/``.db3``) given instead of its folder is accepted when the
    ``metadata.yaml`` beside it names it as the bag's only file: that file holds the
    messages, but the time base, scenario, gaps and biases the tools need are in the
    folder's metadata (``custom_data``), so the folder is what is read. Anything else is a
    :class:`BagError`.
    """
    p = Path(path)
    if p.is_file():
        meta = p.parent / 'metadata.yaml'
        if p.name == 'metadata.yaml' or (p.suffix in _STORAGE_SUFFIXES and meta.is_file()):
            files = _storage_files(bag_metadata(p.parent))
            if p.name == 'metadata.yaml' or files == [p.name]:
                return p.parent
            if p.name in files:
                raise BagError(
                    f'{p} is one of the {len(files)} storage files of the bag {p.parent}; '
                    'give the bag folder'
                )
            raise BagError(f'{p} is not one of the files the bag {p.parent} lists ({files})')
        what = 'an empty file' if p.stat().st_size == 0 else 'a file'
        if p.suffix in _STORAGE_SUFFIXES:
            what += ' with no metadata.yaml beside it'
        raise BagError(
            f'{p} is {what}, not a rosbag2 folder (a folder with metadata.yaml and its '
            '.mcap or .db3 file)'
        )
    if not p.exists():
        raise BagError(f'no bag folder {p}')
    if not p.is_dir():
        raise BagError(f'{p} is not a folder')
    if not (p / 'metadata.yaml').is_file():
        storage = sorted(f.name for f in p.iterdir() if f.suffix in _STORAGE_SUFFIXES)
        raise BagError(
            f'{p} is not a rosbag2 folder: it has no metadata.yaml'
            + (f' (storage files: {", ".join(storage)})' if storage else '')
        )
    return p


_SAFE_LOADER = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)
"""PyYAML's safe loader in C where libyaml is there (a bag's metadata.yaml holds a QoS
profile per topic: the Python loader took a quarter of a second on a 28-topic bag)."""


def bag_metadata(path: str | Path) -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` mapping of a bag's ``metadata.yaml``."""
    folder = Path(path) if Path(path).is_dir() else bag_folder(path)
    meta_path = folder / 'metadata.yaml'
    try:
        meta = yaml.load(meta_path.read_text(), Loader=_SAFE_LOADER)
    except FileNotFoundError:
        bag_folder(folder)  # says what is missing
        raise
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        where = f'line {mark.line + 1}: ' if mark is not None else ''
        problem = getattr(exc, 'problem', None) or _one_line(exc)
        raise BagError(f'{meta_path} is not valid YAML ({where}{problem})') from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise BagError(f'{meta_path} cannot be read: {_one_line(exc)}') from exc
    info = meta.get('rosbag2_bagfile_information') if isinstance(meta, dict) else None
    if not isinstance(info, dict):
        what = 'is empty' if meta is None else 'has no rosbag2_bagfile_information mapping'
        raise BagError(f'{meta_path} {what}: not the metadata of a rosbag2')
    return info


@contextmanager
def _open_reader(path: str | Path) -> Iterator[tuple[Path, Reader]]:
    """An open rosbags reader of a checked bag folder; every failure is a BagError."""
    folder = bag_folder(path)
    info = bag_metadata(folder)
    files = _storage_files(info)
    if not files:
        raise BagError(f'{folder / "metadata.yaml"} lists no storage file')
    missing = [f for f in files if not (folder / f).is_file()]
    if missing:
        raise BagError(
            f'{folder}: metadata.yaml names {", ".join(missing)}, which '
            f'{"is" if len(missing) == 1 else "are"} missing'
        )
    empty = [f for f in files if (folder / f).stat().st_size == 0]
    if empty:
        raise BagError(f'{folder}: {", ".join(empty)} is empty')
    try:
        reader = Reader(folder)
        reader.open()
    except Exception as exc:  # whatever the storage file holds: one line, not a traceback
        raise BagError(
            f'{folder}: cannot open {", ".join(files)}: {_one_line(exc)} '
            '(truncated or not a rosbag2 file?)'
        ) from exc
    try:
        yield folder, reader
    finally:
        reader.close()


_TOPICS_SEEN: dict[tuple[object, ...], dict[str, tuple[str, int]]] = {}
"""Topics of bags already opened, by folder and the size and time of change of its files:
a command asks for them two or three times (checking its input, then reading it), and each
opening parses the metadata anew (a few tenths of a second)."""


def _files_key(folder: Path) -> tuple[object, ...]:
    try:
        files = sorted(
            (e.name, e.stat().st_size, e.stat().st_mtime_ns) for e in os.scandir(folder)
        )
    except OSError:
        return ()
    return (str(folder.resolve()), *files)


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """Topics of a bag (names as recorded) with their message type and count; opening
    the bag checks its metadata and storage files (a bag whose files have not changed since
    it was opened is not opened again)."""
    key = _files_key(bag_folder(path))
    if key and key in _TOPICS_SEEN:
        return dict(_TOPICS_SEEN[key])
    out: dict[str, tuple[str, int]] = {}
    with _open_reader(path) as (_folder, reader):
        for c in reader.connections:
            _, n = out.get(c.topic, (c.msgtype, 0))
            out[c.topic] = (c.msgtype, n + int(c.msgcount))
    if key:
        if len(_TOPICS_SEEN) >= 64:
            _TOPICS_SEEN.clear()
        _TOPICS_SEEN[key] = dict(out)
    return out


def _messages(
    path: str | Path,
    topics: Iterable[str] | None,
    decode: bool,
    raw_types: Collection[str] = (),
) -> Iterator[tuple[Any, int, Any]]:
    """``(connection, log time, message or raw bytes)`` of a bag, every failure a
    :class:`BagError` (see :func:`read_bag`); messages of the types ``raw_types`` stay
    raw bytes."""
    wanted = None if topics is None else {t.lstrip('/') for t in topics}
    with _open_reader(path) as (folder, reader):
        conns = [c for c in reader.connections if wanted is None or c.topic.lstrip('/') in wanted]
        classes = {}
        for c in conns if decode else ():
            if c.msgtype in raw_types:
                continue
            try:
                classes[c.msgtype] = message_class(c.msgtype)
            except (ImportError, AttributeError, ValueError) as exc:
                raise BagError(
                    f'{folder}: topic {c.topic} has message type {c.msgtype}, which is not '
                    f'installed ({_one_line(exc)})'
                ) from exc
        expected = sum(int(c.msgcount) for c in conns)
        messages = reader.messages(connections=conns)
        n = 0
        while True:
            try:
                item = next(messages, None)
                if item is None:
                    break
                conn, t_ns, raw = item
                if decode and conn.msgtype not in raw_types:
                    msg = deserialize_message(raw, classes[conn.msgtype])
                else:
                    msg = raw
            except MemoryError:
                raise
            except Exception as exc:  # a corrupt storage file: one line, not a traceback
                raise BagError(
                    f'{folder}: message {n + 1} of {expected} cannot be read: '
                    f'{_one_line(exc)} (truncated or corrupt file?)'
                ) from exc
            n += 1
            yield conn, t_ns, msg
        if n < expected:
            raise BagError(
                f'{folder}: only {n} of the {expected} messages its index lists could be '
                'read (truncated or corrupt file?)'
            )


def read_bag(
    path: str | Path, topics: Iterable[str] | None = None, raw_types: Collection[str] = ()
) -> Iterator[BagMessage]:
    """Messages of a rosbag2 (MCAP or sqlite3) in log-time order, deserialised by rclpy.

    Parameters
    ----------
    path : path-like
        Bag folder (with ``metadata.yaml``), or its storage file (see :func:`bag_folder`).
    topics : iterable of str, optional
        Only these topics (names as recorded, leading ``/`` optional).
    raw_types : collection of str, optional
        Message types (``sensor_msgs/msg/PointCloud2``) left as their serialised bytes, for
        a reader of its own (:func:`~orbit_tracking.ros.conversions.parse_cloud`).

    Raises
    ------
    BagError
        The bag cannot be opened, a message cannot be read or decoded (also half way
        through), a message type is unknown, or fewer messages could be read than the
        bag's index lists (a storage file cut or overwritten in the middle).
    """
    for conn, t_ns, msg in _messages(path, topics, decode=True, raw_types=raw_types):
        yield BagMessage(conn.topic, conn.msgtype, t_ns, msg)


def scan_bag(path: str | Path) -> int:
    """Read the bytes of every message of a bag (not decoded: a pass at disk speed) and
    return how many there are; what :func:`read_bag` would find wrong with the storage
    files raises :class:`BagError` here, before anything is started on the bag."""
    return sum(1 for _ in _messages(path, None, decode=False))


def bag_custom_data(path: str | Path) -> dict[str, str]:
    """The ``custom_data`` map of a bag's metadata (empty if none)."""
    data = bag_metadata(path).get('custom_data') or {}
    if not isinstance(data, dict):
        raise BagError(f'{bag_folder(path)}: custom_data of metadata.yaml is not a mapping')
    return {str(k): str(v) for k, v in data.items()}
