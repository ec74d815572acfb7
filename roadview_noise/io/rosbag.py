"""ROS bags in and out with ``rosbags`` (pure Python, no ROS install): ROS 1 ``.bag``, ROS 2 bag folders
(``metadata.yaml`` + ``.mcap``/``.db3``) and single ``.mcap``/``.db3`` files.

Reading: every connection with its message definition and hash, messages as raw serialised bytes in record order,
deserialised only where rvnoise changes them. Writing (:func:`bag_output`): a new bag of the input's family whose
connections copy the input's (topic, type, definition, hash, ROS 1 callerid/latching, ROS 2 serialisation format,
QoS, compression: ROS 1 chunks lz4/bz2, ROS 2 zstd per file or message), each message written with its record time;
into a temporary sibling of the output that is renamed onto it only when complete, so no half-written bag exists.

The header stamp of a ``sensor_msgs`` message is read from its first bytes without deserialising it
(:func:`header_stamp_ns`): ROS 1 ``uint32 seq, uint32 sec, uint32 nsec``; CDR a 4-byte encapsulation then
``int32 sec, uint32 nanosec`` in the stated byte order.
"""

from __future__ import annotations

import os
import shutil
import struct
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from ..errors import InputError
from .atomic import TMP_SUFFIX
from .writeback import Writeback

BAG_SUFFIXES = {".bag": "ros1", ".mcap": "ros2", ".db3": "ros2"}


def bag_kind(path: str | os.PathLike) -> str | None:
    """``ros1`` | ``ros2`` for a bag path (a ROS 2 folder has ``metadata.yaml``), else None."""
    path = Path(path)
    if path.is_dir():
        return "ros2" if (path / "metadata.yaml").is_file() else None
    return BAG_SUFFIXES.get(path.suffix.lower())


def output_kind(path: str | os.PathLike) -> str:
    """The family an output path asks for: ``.bag`` ROS 1, anything else (folder, ``.mcap``, ``.db3``) ROS 2."""
    return "ros1" if Path(path).suffix.lower() == ".bag" else "ros2"


def header_stamp_ns(raw: bytes, is2: bool) -> int:
    """Header stamp (ns) of a serialised message that starts with ``std_msgs/Header``."""
    if is2:
        order = "<" if raw[1] else ">"
        sec, nsec = struct.unpack_from(order + "iI", raw, 4)
    else:
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec * 1_000_000_000 + nsec


@contextmanager
def open_bag(path: str | os.PathLike) -> Iterator[Any]:
    """An open ``rosbags`` AnyReader; a bag that cannot be opened (truncated, damaged, not a bag) is an InputError
    naming it."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    kind = bag_kind(path)
    if kind is None:
        raise InputError("not a ROS bag (expected a .bag, .mcap or .db3 file, or a ROS 2 bag folder with "
                         "metadata.yaml)", file=str(path))
    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.LATEST)
    reader = AnyReader([path], default_typestore=store)
    try:
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as exc:
        hint = " (a bag cut short by a killed recorder: run `rosbag reindex` on it)" if kind == "ros1" else ""
        raise InputError(f"cannot read the bag, it is truncated or damaged{hint}: {exc}", file=str(path)) from None
    try:
        yield reader
    finally:
        reader.close()


def temporary_sibling(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}{TMP_SUFFIX}")


def remove_stale_siblings(path: Path) -> None:
    """Delete temporaries a killed run left next to ``path``: :func:`temporary_sibling`'s and ``io/atomic``'s
    (``.<stem>.<pid>.rvnoise-tmp<suffix>``)."""
    for pattern in (f".{path.name}.*{TMP_SUFFIX}*", f".{path.stem}.*{TMP_SUFFIX}{path.suffix}"):
        for p in path.parent.glob(pattern):
            shutil.rmtree(p) if p.is_dir() else p.unlink()


class BagOutput:
    """Connections and messages of the output bag (see :func:`bag_output`)."""

    def __init__(self, writer: Any, reader: Any, is2: bool, writeback: Writeback):
        self.writer, self.writeback = writer, writeback
        self.connections: dict[int, Any] = {}
        for conn in reader.connections:
            self.connections[id(conn)] = self._add(conn, reader.typestore, is2)

    def _add(self, conn: Any, typestore: Any, is2: bool) -> Any:
        msgdef = conn.msgdef.data or None
        if not is2:
            return self.writer.add_connection(conn.topic, conn.msgtype, typestore=typestore, msgdef=msgdef,
                                              md5sum=conn.digest or None, callerid=conn.ext.callerid,
                                              latching=conn.ext.latching)
        return self.writer.add_connection(conn.topic, conn.msgtype, typestore=typestore, msgdef=msgdef,
                                          rihs01=conn.digest or None,
                                          serialization_format=conn.ext.serialization_format,
                                          offered_qos_profiles=conn.ext.offered_qos_profiles)

    def write(self, conn: Any, record_time_ns: int, data: bytes) -> None:
        self.writer.write(self.connections[id(conn)], record_time_ns, data)
        self.writeback.wrote(len(data))


@contextmanager
def bag_output(path: str | os.PathLike, reader: Any) -> Iterator[BagOutput]:
    """A writer of the output bag, in the input's family, renamed onto ``path`` when the block ends without error
    (removed otherwise; an existing output is replaced only then). ``path``: ``.bag`` (ROS 1), a folder (ROS 2 bag,
    the input's storage), or a single ``.mcap``/``.db3`` file (ROS 2)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_sibling(path)
    suffix = path.suffix.lower()
    if output_kind(path) == "ros1":
        writer = Writer1(tmp)
        compression = _ros1_compression(reader)
        if compression:
            writer.set_compression(Writer1.CompressionFormat[compression.upper()])
        made = data_file = tmp
    else:
        # rosbags names the storage file after the bag folder: write tmp/<name>/<name>.mcap, then move it in place
        tmp.mkdir()
        single = suffix in (".mcap", ".db3")
        storage = suffix if single else _input_storage(reader)
        plugin = StoragePlugin.MCAP if storage == ".mcap" else StoragePlugin.SQLITE3
        folder = tmp / (path.stem if single else path.name)
        writer = Writer2(folder, version=Writer2.VERSION_LATEST, storage_plugin=plugin)
        mode = reader.readers[0].compression_mode
        if mode:
            writer.set_compression(CompressionMode[mode.upper()], CompressionFormat.ZSTD)
        made = folder / f"{folder.name}{storage}" if single else folder
        data_file = folder / f"{folder.name}{storage}" if storage == ".mcap" else None   # sqlite writes its own
    try:
        writer.open()
        writeback = Writeback(data_file)
        try:
            yield BagOutput(writer, reader, is2=output_kind(path) == "ros2", writeback=writeback)
        finally:
            writeback.close()
        writer.close()
        for p in ([made] if made.is_file() else sorted(made.iterdir())):
            _fsync(p)
        _replace(made, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp) if tmp.is_dir() else tmp.unlink()


def _ros1_compression(reader: Any) -> str | None:
    """``lz4`` | ``bz2`` when chunks of the ROS 1 input are compressed (lz4 if both occur), else None."""
    from rosbags.rosbag1.reader import decompressors

    names = {id(f): name for name, f in decompressors.items()}
    used = {names.get(id(c.decompressor)) for r in reader.readers for c in getattr(r, "chunks", {}).values()}
    return next((c for c in ("lz4", "bz2") if c in used), None)


def _input_storage(reader: Any) -> str:
    """``.mcap`` or ``.db3``: the storage of a ROS 2 input."""
    path = Path(reader.paths[0])
    if path.is_file():
        return path.suffix.lower()
    return ".mcap" if any(path.glob("*.mcap")) else ".db3"


def _fsync(path: Path) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def _replace(tmp: Path, path: Path) -> None:
    """Rename ``tmp`` onto ``path``; an existing folder is moved aside first and removed after."""
    if path.is_dir() and not path.is_symlink():
        old = path.with_name(f".{path.name}.{os.getpid()}.old{TMP_SUFFIX}")
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old)
    elif path.exists() and tmp.is_dir():
        path.unlink()
        os.replace(tmp, path)
    else:
        os.replace(tmp, path)
