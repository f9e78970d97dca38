"""rosbag2 files: written and read with ``rosbags``; message bytes are CDR produced and
parsed by ``rclpy.serialization``, so a bag written here is read by ``ros2 bag play`` and
a bag recorded by ``ros2 bag record`` is read here.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable, Iterator
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

__all__ = ['BagMessage', 'BagWriter', 'bag_custom_data', 'message_class', 'msgtype_of', 'read_bag']

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


def read_bag(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Messages of a rosbag2 (MCAP or sqlite3) in log-time order, deserialised by rclpy.

    Parameters
    ----------
    path : path-like
        Bag folder (with ``metadata.yaml``).
    topics : iterable of str, optional
        Only these topics (names as recorded, leading ``/`` optional).
    """
    wanted = None if topics is None else {t.lstrip('/') for t in topics}
    with Reader(Path(path)) as reader:
        conns = [c for c in reader.connections if wanted is None or c.topic.lstrip('/') in wanted]
        classes = {c.msgtype: message_class(c.msgtype) for c in conns}
        for conn, t_ns, raw in reader.messages(connections=conns):
            yield BagMessage(
                conn.topic, conn.msgtype, t_ns, deserialize_message(raw, classes[conn.msgtype])
            )


def bag_custom_data(path: str | Path) -> dict[str, str]:
    """The ``custom_data`` map of a bag's metadata (empty if none)."""
    meta = yaml.safe_load((Path(path) / 'metadata.yaml').read_text())
    data = meta.get('rosbag2_bagfile_information', {}).get('custom_data') or {}
    return {str(k): str(v) for k, v in data.items()}
