"""Bag files without DDS: the typestore, a splitting rosbag2/MCAP writer and a batch reader.

Bags are rosbag2 version 9 directories with MCAP storage, written through rosbags' `Writer`, so a
full Jazzy install can `ros2 bag play` them and rosbags' AnyReader / the `mcap` package read them.
No rclpy here: offline tools (identification, mapping, insertion experiments) read bags with
`read_messages` as fast as the CPU allows. A sound bag is read with rosbags' `Reader`; a damaged
one (no metadata.yaml, a file without footer or summary) is recovered file by file with the `mcap`
package's `StreamReader` (`_scan_mcap`). Either read stops at a chunk it cannot read and keeps
every message before it.
"""
from __future__ import annotations

import heapq
import io
import shutil
import warnings
import zlib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from enum import Enum, StrEnum
from pathlib import Path
from types import TracebackType
from typing import IO, Any, NamedTuple, assert_never, cast

import lz4.frame
import zstandard
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.records import Channel as McapChannel
from mcap.records import Chunk, Footer, McapRecord, Message, Schema
from mcap.stream_reader import StreamReader
from rosbags.interfaces import (
    ConnectionExtRosbag2,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import (
    CompressionFormat,
    CompressionMode,
    Reader,
    ReaderError,
    StoragePlugin,
    Writer,
    WriterError,
)
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore
from ruamel.yaml import YAML, YAMLError

from coop_common.params import choice

from .errors import BagError

#: Interface packages of this project whose .msg files are registered in every typestore.
PROJECT_INTERFACE_PACKAGES: tuple[str, ...] = ('coop_msgs',)


class Compression(StrEnum):
    """BagWriter's MCAP chunk compression (the recorder's `compression` parameter)."""

    NONE = 'none'
    ZSTD = 'zstd'


#: MCAP chunk compression choices of BagWriter
COMPRESSIONS = tuple(Compression)


class BagNotFoundError(BagError, FileNotFoundError):
    """The bag path (or a file its metadata names) does not exist."""


class UnknownTypeError(BagError, KeyError):
    """A message type is neither in the typestore nor defined by the bag or the ament index."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ''


class DamagedBagError(BagError):
    """A bag is truncated or lacks metadata; `problems` names each defect. Raised by strict reads
    only after every still readable message has been yielded."""

    def __init__(self, problems: Sequence[str]) -> None:
        super().__init__('; '.join(problems))
        self.problems = list(problems)


class DamagedBagWarning(UserWarning):
    """Non-strict reads warn with this instead of raising DamagedBagError."""


# ---------------------------------------------------------------------------------------------
# Types
# ---------------------------------------------------------------------------------------------

def _share_dir(package: str) -> Path | None:
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory  # noqa: PLC0415 - optional dependency
    except ImportError:  # pragma: no cover - ament_index_python is in the venv
        return None
    try:
        return Path(get_package_share_directory(package))
    except (PackageNotFoundError, ValueError, LookupError):
        return None


def register_package_msgs(typestore: Typestore, package: str,
                          share_dir: Path | None = None) -> list[str]:
    """Register every `<share>/<package>/msg/*.msg` of `package` (srv/action are not topics).

    Returns the registered type names. Raises UnknownTypeError when the package is not found."""
    share = share_dir if share_dir is not None else _share_dir(package)
    if share is None or not (share / 'msg').is_dir():
        raise UnknownTypeError(f'interface package {package!r} not found on the ament index '
                               '(is the workspace built and sourced?)')
    types: dict[str, Any] = {}
    for path in sorted((share / 'msg').glob('*.msg')):
        types.update(get_types_from_msg(path.read_text(), f'{package}/msg/{path.stem}'))
    typestore.register(types)
    return sorted(types)


def make_typestore(packages: Iterable[str] = PROJECT_INTERFACE_PACKAGES) -> Typestore:
    """Jazzy's standard types plus the project's interface packages, registered from .msg files."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    for package in packages:
        register_package_msgs(typestore, package)
    return typestore


def ensure_type(typestore: Typestore, msgtype: str) -> None:
    """Make `msgtype` ('pkg/msg/Name') known, loading its package's .msg files from the ament index
    when it is not yet registered. Raises UnknownTypeError naming the type."""
    if msgtype in typestore.fielddefs:
        return
    parts = msgtype.split('/')
    if len(parts) != 3 or parts[1] != 'msg':
        raise UnknownTypeError(f'{msgtype!r} is not a message type name (pkg/msg/Name)')
    try:
        register_package_msgs(typestore, parts[0])
    except UnknownTypeError as exc:
        raise UnknownTypeError(f'unknown message type {msgtype!r}: {exc}') from None
    if msgtype not in typestore.fielddefs:
        raise UnknownTypeError(f'unknown message type {msgtype!r}: package {parts[0]!r} has no '
                               f'{parts[2]}.msg')


# ---------------------------------------------------------------------------------------------
# QoS as recorded in metadata (rosbags' Qos), independent of rclpy
# ---------------------------------------------------------------------------------------------

_INFINITE = QosTime(9223372036, 854775807)   # how rosbag2 writes an infinite duration


def make_qos(*, reliable: bool, transient_local: bool, depth: int = 10,
             keep_all: bool = False) -> Qos:
    """A rosbag2 offered-QoS entry with the policies that matter for matching."""
    return Qos(
        history=QosHistory.KEEP_ALL if keep_all else QosHistory.KEEP_LAST,
        depth=depth,
        reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
        durability=(QosDurability.TRANSIENT_LOCAL if transient_local
                    else QosDurability.VOLATILE),
        deadline=_INFINITE, lifespan=_INFINITE, liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=_INFINITE, avoid_ros_namespace_conventions=False)


# rosbag2 writes each QoS policy by its lower-case name (metadata version 9) or number (8)
_QOS_POLICIES: tuple[tuple[str, type[Enum]], ...] = (
    ('history', QosHistory), ('reliability', QosReliability), ('durability', QosDurability),
    ('liveliness', QosLiveliness))
_QOS_TIMES: tuple[str, ...] = ('deadline', 'lifespan', 'liveliness_lease_duration')


def dump_offered_qos(profiles: Sequence[Qos]) -> list[dict[str, Any]]:
    """Offered QoS profiles as rosbag2 writes them (metadata version 9) into metadata.yaml and an
    MCAP channel's `offered_qos_profiles`: policies by lower-case name, durations as sec/nsec."""
    def duration(t: QosTime) -> dict[str, int]:
        return {'sec': t.sec, 'nsec': t.nsec}

    return [{
        'history': q.history.name.lower(),
        'depth': q.depth,
        'reliability': q.reliability.name.lower(),
        'durability': q.durability.name.lower(),
        'deadline': duration(q.deadline),
        'lifespan': duration(q.lifespan),
        'liveliness': q.liveliness.name.lower(),
        'liveliness_lease_duration': duration(q.liveliness_lease_duration),
        'avoid_ros_namespace_conventions': q.avoid_ros_namespace_conventions,
    } for q in profiles]


def parse_offered_qos(text: str) -> list[Qos]:
    """The offered QoS profiles of rosbag2's YAML (an MCAP channel's `offered_qos_profiles`;
    policies by name as version 9 writes them, or by number as version 8 did). '' gives [].
    Raises BagError naming the first malformed entry."""
    try:
        entries = YAML(typ='safe').load(text) if text.strip() else []
    except YAMLError as exc:
        raise BagError(f'offered_qos_profiles is not YAML: {exc}') from None
    if entries is None:
        return []
    if not isinstance(entries, list):
        raise BagError(f'offered_qos_profiles is not a list: {entries!r}')
    return [_qos_from_entry(i, e) for i, e in enumerate(entries)]


def _qos_from_entry(index: int, entry: Any) -> Qos:
    where = f'offered_qos_profiles[{index}]'
    if not isinstance(entry, dict):
        raise BagError(f'{where} is not a mapping: {entry!r}')
    try:
        policies: dict[str, Any] = {}
        for key, enum in _QOS_POLICIES:
            value = entry[key]
            try:
                policies[key] = (enum(value) if isinstance(value, int)
                                 else enum[str(value).upper()])
            except (KeyError, ValueError):
                raise BagError(f'{where}.{key}: {value!r} is not one of '
                               f'{[m.name.lower() for m in enum]}') from None
        times: dict[str, Any] = {key: QosTime(int(entry[key]['sec']), int(entry[key]['nsec']))
                 for key in _QOS_TIMES}
        avoid = entry['avoid_ros_namespace_conventions']
        if not isinstance(avoid, bool):
            raise BagError(f'{where}.avoid_ros_namespace_conventions: {avoid!r} is not a bool')
        return Qos(depth=int(entry['depth']), avoid_ros_namespace_conventions=avoid,
                   **policies, **times)
    except KeyError as exc:
        raise BagError(f'{where} has no {exc.args[0]!r}') from None
    except (TypeError, ValueError) as exc:
        raise BagError(f'{where} is malformed: {exc}') from None


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------

class _SplitFile:
    """One split file of a bag, written by rosbags' public `Writer` (MCAP storage, rosbag2 v9).

    rosbags writes a bag directory `<dir>/<dir>.mcap` + `metadata.yaml`; a split rosbag2 bag holds
    `<bag>_<i>.mcap` files in one directory. So file i is written as the bag `<bag>/<bag>_<i>/`
    and, once closed, its MCAP file is moved up to `<bag>/<bag>_<i>.mcap` and its metadata kept
    in memory for the bag's metadata.yaml."""

    def __init__(self, bag: Path, index: int, compression: Compression) -> None:
        self.name = f'{bag.name}_{index}.mcap'
        self.file_path = bag / self.name            # where the file is once closed
        self.dir = bag / f'{bag.name}_{index}'      # rosbags' bag of this one file
        self.writer = Writer(self.dir, version=9, storage_plugin=StoragePlugin.MCAP)
        match compression:
            case Compression.NONE:
                pass
            case Compression.ZSTD:
                # MCAP chunk compression: transparent to every MCAP reader (ros2 bag play
                # included); the rosbag2 metadata keeps compression_mode '' as rosbag2's own MCAP
                # presets do
                self.writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            case _:
                assert_never(compression)
        self.writer.open()
        self.messages = 0

    def add_connection(self, spec: TopicSpec, typestore: Typestore) -> Any:
        return self.writer.add_connection(
            spec.name, spec.msgtype, typestore=typestore, rihs01=spec.type_hash,
            msgdef=typestore.generate_msgdef(spec.msgtype, ros_version=2)[0],
            offered_qos_profiles=spec.offered_qos)

    def write(self, conn: Any, t_ns: int, data: bytes | memoryview) -> None:
        self.writer.write(conn, t_ns, data)
        self.messages += 1

    def close(self) -> dict[str, Any] | None:
        """Finish the file; its rosbag2 metadata, or None (and no file) if it holds nothing."""
        if not self.messages:
            self.abort()
            shutil.rmtree(self.dir, ignore_errors=True)
            return None
        self.writer.close()

        meta = self.dir / 'metadata.yaml'
        info = YAML(typ='safe').load(meta.read_text())['rosbag2_bagfile_information']
        (self.dir / self.name).replace(self.file_path)
        meta.unlink()
        self.dir.rmdir()
        return info

    def abort(self) -> None:
        """Stop without finishing the file (what a crash leaves)."""
        self.writer.abort()


@dataclass
class TopicSpec:
    """A topic's connection data: type, offered QoS, RIHS01 type hash."""

    name: str
    msgtype: str
    offered_qos: list[Qos] = field(default_factory=list)
    type_hash: str = ''


class BagWriter:
    """A rosbag2 v9 MCAP bag written with rosbags, split by size and/or duration.

    with BagWriter(path, max_bytes=100 << 20) as bag:
        bag.add_topic('/rover1/imu', 'sensor_msgs/msg/Imu', offered_qos=[make_qos(...)])
        bag.write('/rover1/imu', t_ns, cdr_bytes)

    `compression='zstd'` compresses MCAP chunks (stereo images shrink several-fold).
    Split files are `<path>/<name>_<i>.mcap` as rosbag2 names them, each written by rosbags'
    public `Writer` (`_SplitFile`); metadata.yaml (listing all of them) is written by `close()`.
    `flush()` finishes the current file, so a killed process leaves every message up to the
    last flush in complete files (`read_messages` reads them without metadata.yaml); each flush
    that follows new messages therefore adds a split file.
    """

    def __init__(self, path: str | Path, *, typestore: Typestore | None = None,
                 max_bytes: int = 0, max_duration_s: float = 0.0,
                 compression: Compression | str = Compression.NONE,
                 custom_data: dict[str, str] | None = None) -> None:
        self.path = Path(path)
        self.compression = choice(Compression, compression, 'compression')
        if self.path.exists():
            raise BagError(f'{self.path} exists already; a bag is never overwritten')
        if max_bytes < 0 or max_duration_s < 0:
            raise ValueError('max_bytes and max_duration_s must be >= 0 (0: no splitting)')
        self.typestore = typestore if typestore is not None else make_typestore()
        self.max_bytes = int(max_bytes)
        self.max_duration_ns = int(max_duration_s * 1e9)
        self.custom_data = dict(custom_data or {})
        self.topics: dict[str, TopicSpec] = {}
        self.counts: dict[str, int] = {}
        self._files: list[dict[str, Any]] = []    # closed files' metadata
        self._file: _SplitFile | None = None
        self._conns: dict[str, Any] = {}
        self._file_start_ns: int | None = None
        self._file_bytes = 0
        self._closed = False
        self.path.mkdir(parents=True)

    # -- topics -----------------------------------------------------------------------------
    def add_topic(self, name: str, msgtype: str, *, offered_qos: Sequence[Qos] = (),
                  type_hash: str | None = None) -> TopicSpec:
        """Register a topic (idempotent for the same type). Raises UnknownTypeError for a type the
        typestore cannot define and BagError for a topic re-added with another type."""
        if name in self.topics:
            if self.topics[name].msgtype != msgtype:
                raise BagError(f'topic {name!r} already recorded as {self.topics[name].msgtype}, '
                               f'cannot add it as {msgtype}')
            return self.topics[name]
        ensure_type(self.typestore, msgtype)
        computed = self.typestore.hash_rihs01(msgtype)
        spec = TopicSpec(name, msgtype, list(offered_qos), type_hash or computed)
        self.topics[name] = spec
        self.counts[name] = 0
        if self._file is not None:
            self._add_connection(spec)
        return spec

    def _add_connection(self, spec: TopicSpec) -> None:
        assert self._file is not None
        self._conns[spec.name] = self._file.add_connection(spec, self.typestore)

    # -- writing ----------------------------------------------------------------------------
    def _open_file(self) -> None:
        index = len(self._files)
        self._file = _SplitFile(self.path, index, self.compression)
        self._conns = {}
        self._file_start_ns = None
        self._file_bytes = 0
        for spec in self.topics.values():
            self._add_connection(spec)

    def _close_file(self) -> None:
        file, self._file = self._file, None
        if file is None:
            return
        info = file.close()
        if info is not None:
            self._files.append(info)

    def write(self, topic: str, t_ns: int, data: bytes | memoryview) -> None:
        """Write one serialized (CDR) message received at `t_ns`."""
        if self._closed:
            raise BagError(f'{self.path}: bag is closed')
        spec = self.topics.get(topic)
        if spec is None:
            raise BagError(f'topic {topic!r} was not added to {self.path}')
        if self._file is not None and self._file_start_ns is not None and (
                (self.max_bytes and self._file_bytes >= self.max_bytes)
                or (self.max_duration_ns
                    and t_ns - self._file_start_ns >= self.max_duration_ns)):
            self._close_file()
        if self._file is None:
            self._open_file()
        if self._file_start_ns is None:
            self._file_start_ns = t_ns
        assert self._file is not None                # _open_file opened one
        self._file.write(self._conns[topic], t_ns, data)
        self._file_bytes += len(data) + 31   # message record + index entry
        self.counts[topic] += 1

    def flush(self) -> None:
        """Make every message written so far survive a killed process: the current split file
        is finished (a complete MCAP file, index and summary included) and the next message
        starts a new one. rosbags' public Writer buffers up to 1 MiB per chunk and offers no
        flush of its own. Not fsync: a killed process, not a power cut. Nothing to do when no
        message came since the last flush."""
        if self._file is not None and self._file.messages:
            self._close_file()

    @property
    def files(self) -> list[Path]:
        names = [self.path / f['relative_file_paths'][0] for f in self._files]
        if self._file is not None:
            names.append(self._file.dir / self._file.name)     # moved up when closed
        return names

    def close(self) -> Path:
        """Close the current file and write metadata.yaml for all files. Idempotent."""
        if self._closed:
            return self.path
        self._closed = True
        self._close_file()
        self._write_metadata()
        return self.path

    def _write_metadata(self) -> None:

        starts = [f['starting_time']['nanoseconds_since_epoch'] for f in self._files]
        ends = [f['starting_time']['nanoseconds_since_epoch'] + f['duration']['nanoseconds']
                for f in self._files]
        start = min(starts) if starts else 0
        duration = (max(ends) - start) if ends else 0
        info = {
            'version': 9,
            'storage_identifier': 'mcap',
            'relative_file_paths': [f['relative_file_paths'][0] for f in self._files],
            'duration': {'nanoseconds': duration},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': sum(self.counts.values()),
            'topics_with_message_count': [{
                'topic_metadata': {
                    'name': s.name, 'type': s.msgtype, 'serialization_format': 'cdr',
                    'offered_qos_profiles': dump_offered_qos(s.offered_qos),
                    'type_description_hash': s.type_hash,
                },
                'message_count': self.counts[s.name],
            } for s in self.topics.values()],
            'compression_format': '',
            'compression_mode': '',
            'files': [f['files'][0] for f in self._files],
            'custom_data': self.custom_data or None,
            'ros_distro': 'jazzy',
        }
        yaml = YAML(typ='safe')
        yaml.default_flow_style = False
        yaml.width = 4096          # no folded hashes: one `key: value` line as rosbag2 writes
        tmp = self.path / 'metadata.yaml.tmp'
        with tmp.open('w') as out:
            yaml.dump({'rosbag2_bagfile_information': info}, out)
        tmp.replace(self.path / 'metadata.yaml')

    def abort(self) -> None:
        """Stop without metadata (what a crash leaves, minus unflushed data)."""
        self._closed = True
        if self._file is not None:
            self._file.abort()
            self._file = None

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------

class BagMessage(NamedTuple):
    """One message of a bag: `msg` is the deserialized message, or CDR bytes with raw=True."""

    topic: str
    msgtype: str
    t_ns: int
    msg: Any


@dataclass
class TopicInfo:
    """One topic of a bag: its type, message count, offered QoS and type description."""

    name: str
    msgtype: str
    count: int
    offered_qos: list[Qos]
    type_hash: str = ''
    msgdef: str = ''


@dataclass
class BagInfo:
    """What a bag holds, and what is wrong with it (`problems` empty for a sound bag)."""

    path: Path
    files: list[Path]
    topics: dict[str, TopicInfo]
    start_ns: int
    end_ns: int
    message_count: int
    problems: list[str]
    recovered: bool     # files recovered with mcap's StreamReader (no usable metadata/index)

    @property
    def duration_s(self) -> float:
        return max(0, self.end_ns - self.start_ns) / 1e9


@dataclass
class _Channel:
    topic: str
    msgtype: str
    qos: list[Qos]
    msgdef: str


@dataclass
class _ScanResult:
    """What the recovery read of one MCAP file found: its channels, its messages as
    (t_ns, channel id, data) in file order, and the defects that stopped or marred the read."""

    channels: dict[int, _Channel] = field(default_factory=dict)
    messages: list[tuple[int, int, bytes]] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)


class _ExactReader(io.BufferedIOBase):
    """Bytes for mcap's StreamReader handed out exactly as asked or not at all: a read past the
    end raises mcap's EndOfFile, so a record cut off by the end of the data is never parsed from
    a short read. `pos` counts the bytes handed out."""

    def __init__(self, raw: IO[bytes], size: int) -> None:
        super().__init__()
        self._raw = raw
        self.size = size
        self.pos = 0

    def readable(self) -> bool:
        return True

    def read(self, size: int | None = -1, /) -> bytes:
        if size is None or size < 0:    # from a corrupt length field; would read everything
            raise McapError(f'negative field length at byte {self.pos}')
        if size > self.size - self.pos:
            raise EndOfFile()
        data = self._raw.read(size)
        if len(data) != size:           # the file shrank while it was read
            raise EndOfFile()
        self.pos += size
        return data


class _ChunkError(BagError):
    """A chunk whose records cannot be trusted (caught by the recovery read)."""


def _chunk_records(chunk: Chunk) -> list[McapRecord]:
    """All records of an MCAP chunk, or _ChunkError: the data decompressed, checked against the
    chunk's uncompressed size and CRC (when its writer set one), and read by mcap's StreamReader
    to exactly the chunk's end."""
    try:
        # the MCAP specification's chunk compressions: none, zstd, lz4
        match chunk.compression:
            case '':
                raw = chunk.data
            case 'zstd':
                raw = zstandard.ZstdDecompressor().decompress(
                    chunk.data, max_output_size=chunk.uncompressed_size)
            case 'lz4':
                raw = lz4.frame.decompress(chunk.data)
            case _:
                raise _ChunkError(f"unknown compression {chunk.compression!r} (MCAP's are '', "
                                  f"'zstd' and 'lz4')")
    except (zstandard.ZstdError, RuntimeError) as exc:      # lz4 raises RuntimeError
        raise _ChunkError(f'{chunk.compression} data do not decompress ({exc})') from None
    if len(raw) != chunk.uncompressed_size:
        raise _ChunkError(f'{len(raw)} bytes where the chunk says {chunk.uncompressed_size}')
    if chunk.uncompressed_crc and zlib.crc32(raw) != chunk.uncompressed_crc:
        raise _ChunkError('CRC mismatch')
    records: list[McapRecord] = []
    if not raw:
        return records
    stream = _ExactReader(io.BytesIO(raw), len(raw))
    try:
        # (StreamReader reads any readable binary stream; its annotation names a few)
        for record in StreamReader(cast(IO[bytes], stream), skip_magic=True).records:
            records.append(record)
            if stream.pos == len(raw):
                return records
    except EndOfFile:
        raise _ChunkError('a record runs past the end of the chunk') from None
    except (McapError, ValueError) as exc:           # UnicodeDecodeError is a ValueError
        raise _ChunkError(f'corrupt record ({exc})') from None
    raise _ChunkError('a footer inside the chunk')


def _scan_channel(name: str, record: McapChannel, schema: Schema | None,
                  problems: list[str]) -> _Channel:
    try:
        qos = parse_offered_qos(record.metadata.get('offered_qos_profiles', ''))
    except BagError as exc:
        problems.append(f'{name}: topic {record.topic}: {exc}; its offered QoS is unknown')
        qos = []
    if schema is None:
        return _Channel(record.topic, '', qos, '')
    msgdef = schema.data.decode(errors='replace') if schema.encoding == 'ros2msg' else ''
    return _Channel(record.topic, schema.name, qos, msgdef)


def _scan_mcap(path: Path) -> _ScanResult:
    """Recover what an MCAP file holds without its summary or index: mcap's StreamReader reads
    it record by record from the start, and the read stops at the first record that is cut off
    (a killed writer, no footer) or corrupt (a bad chunk), keeping every message before it. A
    chunk's messages are kept only when the whole chunk is sound."""
    res = _ScanResult()
    schemas: dict[int, Schema] = {}

    def take(record: McapRecord) -> None:
        if isinstance(record, Message):
            res.messages.append((record.log_time, record.channel_id, record.data))
        elif isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, McapChannel) and record.id not in res.channels:
            res.channels[record.id] = _scan_channel(path.name, record,
                                                    schemas.get(record.schema_id), res.problems)

    size = path.stat().st_size
    done = 0                    # end of the last record read whole
    footer = False
    with path.open('rb') as fh:
        stream = _ExactReader(fh, size)
        try:
            for record in StreamReader(cast(IO[bytes], stream), emit_chunks=True).records:
                if isinstance(record, Chunk):
                    try:
                        inner = _chunk_records(record)
                    except _ChunkError as exc:
                        res.problems.append(f'{path.name}: corrupt chunk at byte {done}: {exc} '
                                            f'({size - done} bytes from there unread)')
                        return res
                    for rec in inner:
                        take(rec)
                else:
                    footer = isinstance(record, Footer)
                    take(record)
                done = stream.pos
        except InvalidMagic:
            res.problems.append(f'{path.name}: not an MCAP file (bad magic)')
        except EndOfFile:
            if footer:
                what = 'after the MCAP footer (end magic cut off)'
            elif done == 0:
                what = f'at byte 0 of {size} (no complete MCAP header)'
            elif done < size:
                what = (f'at byte {done} of {size} (no MCAP footer; {size - done} trailing bytes '
                        'unreadable)')
            else:
                what = f'between records: no MCAP footer ({size} bytes)'
            res.problems.append(f'{path.name}: truncated {what}')
        except (McapError, ValueError) as exc:
            res.problems.append(f'{path.name}: corrupt record at byte {done}: {exc} '
                                f'({size - done} bytes from there unread)')
    return res


class _Source:
    """Where a bag's messages come from: rosbags' indexed Reader, or the recovery read of each
    MCAP file (`_scan_mcap`) when the bag has no readable metadata.yaml or rosbags cannot open
    it (a file without footer or summary)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.problems: list[str] = []
        self.reader: Reader | None = None
        self.scans: list[_ScanResult] = []
        self._last_t: int | None = None     # of the last message an indexed read yielded
        indexed_error = ''
        if not path.exists():
            raise BagNotFoundError(f'bag {str(path)!r} does not exist')
        if path.is_file():
            if path.suffix != '.mcap':
                raise BagError(f'{path}: not a bag directory or an .mcap file')
            self.files = [path]
            self._scan_all()
            return
        meta = path / 'metadata.yaml'
        if meta.is_file():
            try:
                doc = YAML(typ='safe').load(meta.read_text())
                names = doc['rosbag2_bagfile_information']['relative_file_paths']
            except Exception as exc:  # noqa: BLE001 - any defect of the YAML is reported
                self.problems.append(f'{meta.name}: unreadable ({exc}); recovered from the '
                                     'MCAP files')
            else:
                self.files = [path / Path(p).name for p in names]
                missing = [f.name for f in self.files if not f.exists()]
                if missing:
                    raise BagNotFoundError(f'{path}: metadata.yaml names missing file(s) '
                                           f'{missing}')
                reader = Reader(path)
                try:
                    reader.open()
                except ReaderError as exc:
                    indexed_error = str(exc)
                else:
                    self.reader = reader
                    return
        else:
            self.problems.append(f'{path.name}: no metadata.yaml (recorder did not close the '
                                 'bag); recovered from the MCAP files')
        # closed split files, and the one a killed writer left in its own directory
        # (`_SplitFile`: <bag>/<bag>_<i>/<bag>_<i>.mcap)
        self.files = sorted([*path.glob('*.mcap'),
                             *(f for f in path.glob('*/*.mcap') if f.parent.name == f.stem)],
                            key=_split_index)
        if not self.files:
            raise BagNotFoundError(f'{path}: no metadata.yaml and no .mcap file')
        self._scan_all()
        if indexed_error and not self.problems:     # the files read whole: the index is at fault
            self.problems.append(f'indexed read failed ({indexed_error}); recovered from the '
                                 'MCAP files')

    def _scan_all(self) -> None:
        for f in self.files:
            scan = _scan_mcap(f)
            self.problems.extend(scan.problems)
            self.scans.append(scan)

    def topics(self) -> dict[str, TopicInfo]:
        out: dict[str, TopicInfo] = {}
        if self.reader is not None:
            for c in self.reader.connections:
                assert isinstance(c.ext, ConnectionExtRosbag2)      # a rosbag2 reader's
                info = out.setdefault(c.topic, TopicInfo(c.topic, c.msgtype, 0,
                                                         list(c.ext.offered_qos_profiles),
                                                         c.digest, c.msgdef.data))
                info.count += c.msgcount
            return out
        for scan in self.scans:
            counts: dict[int, int] = {}
            for _t, cid, _d in scan.messages:
                counts[cid] = counts.get(cid, 0) + 1
            for cid, ch in scan.channels.items():
                info = out.setdefault(ch.topic, TopicInfo(ch.topic, ch.msgtype, 0, ch.qos, '',
                                                          ch.msgdef))
                info.count += counts.get(cid, 0)
        return out

    def messages(self, topics: set[str] | None) -> Iterator[tuple[str, str, int, bytes]]:
        if self.reader is None:
            yield from self._recovered_messages(topics)
            return
        # a chunk of a file with a sound index may still be unreadable: rosbags raises
        # ReaderError, but lets the errors of its zstd and lz4 decompressors out as they are
        try:
            yield from self._indexed_messages(self.reader, topics)
        except Exception as exc:  # noqa: BLE001 - see above; the messages before it stay
            where = ('no message readable' if self._last_t is None
                     else f'nothing readable after t={self._last_t} ns')
            self.problems.append(f'{self.path.name}: {where} ({type(exc).__name__}: {exc})')

    def _indexed_messages(self, reader: Reader, topics: set[str] | None
                          ) -> Iterator[tuple[str, str, int, bytes]]:
        if len(self.files) == 1:
            conns = [c for c in reader.connections if topics is None or c.topic in topics]
            for c, t, data in reader.messages(connections=conns):
                self._last_t = t
                yield c.topic, c.msgtype, t, data
            return
        # rosbags reads split files one after the other, but a recorder writes in arrival order,
        # so a file may begin with messages older than the previous file's last (receive stamps
        # taken on several threads): merge the files' streams by time. Each file is opened on its
        # own, so a bag's message compression (a metadata.yaml setting) is undone here.
        unzip = (zstandard.ZstdDecompressor() if reader.compression_mode == 'message'
                 else None)

        def stream(file: Path) -> Iterator[tuple[int, str, str, bytes]]:
            with Reader(file) as one:          # rosbags opens a lone storage file too
                conns = [c for c in one.connections if topics is None or c.topic in topics]
                if conns:
                    for c, t, raw in one.messages(connections=conns):
                        data = raw if unzip is None else unzip.decompressobj().decompress(raw)
                        yield t, c.topic, c.msgtype, data
        for t, topic, msgtype, data in heapq.merge(*map(stream, self.files),
                                                  key=lambda m: m[0]):
            self._last_t = t
            yield topic, msgtype, t, data

    def _recovered_messages(self, topics: set[str] | None
                            ) -> Iterator[tuple[str, str, int, bytes]]:
        streams = []
        for scan in self.scans:
            chans = scan.channels
            msgs = sorted(((t, i, cid, d) for i, (t, cid, d) in enumerate(scan.messages)
                           if cid in chans and (topics is None or chans[cid].topic in topics)),
                          key=lambda m: (m[0], m[1]))
            streams.append([(t, chans[cid].topic, chans[cid].msgtype, d)
                            for t, _i, cid, d in msgs])
        for t, topic, msgtype, data in heapq.merge(*streams, key=lambda m: m[0]):
            yield topic, msgtype, t, data

    def close(self) -> None:
        if self.reader is not None:
            self.reader.close()


def _split_index(p: Path) -> tuple[int, str]:
    tail = p.stem.rsplit('_', 1)[-1]
    return (int(tail) if tail.isdigit() else -1, p.name)


def bag_info(path: str | Path) -> BagInfo:
    """Topics, counts, time span and defects of a bag (directory or single .mcap file)."""
    src = _Source(Path(path))
    try:
        topics = src.topics()
        if src.reader is not None:
            start, end = src.reader.start_time, src.reader.end_time - 1
            count = src.reader.message_count
        else:
            times = [t for s in src.scans for t, cid, _ in s.messages if cid in s.channels]
            start, end = (min(times), max(times)) if times else (0, 0)
            count = len(times)
        return BagInfo(Path(path), src.files, topics, start, max(start, end), count,
                       list(src.problems), src.reader is None)
    finally:
        src.close()


def _register_bag_types(typestore: Typestore, topics: Iterable[TopicInfo]) -> list[str]:
    """Make every topic's type known: typestore, else the bag's own definition, else the ament
    index. Returns the 'topic (type)' entries that stay unknown."""
    unknown = []
    for info in topics:
        if info.msgtype in typestore.fielddefs:
            continue
        if info.msgdef:
            try:
                typestore.register(get_types_from_msg(info.msgdef, info.msgtype))
                continue
            except Exception:  # noqa: BLE001 - fall back to the ament index
                pass
        try:
            ensure_type(typestore, info.msgtype)
        except UnknownTypeError:
            unknown.append(f'{info.name} ({info.msgtype})')
    return unknown


def read_messages(path: str | Path, topics: Iterable[str] | None = None, *, raw: bool = False,
                  strict: bool = True, typestore: Typestore | None = None
                  ) -> Iterator[BagMessage]:
    """Yield (topic, msgtype, t_ns, msg) of a bag in time order, without DDS.

    `path`: a bag directory or one .mcap file. `topics`: only these (None: all). `raw=True`
    yields CDR bytes (no deserialization). A damaged bag (truncated file, no metadata.yaml) is
    read as far as its files allow; then `strict=True` raises DamagedBagError naming the defects,
    `strict=False` warns with DamagedBagWarning. A topic whose type is unknown (not in the
    typestore, the bag or the ament index) raises UnknownTypeError before anything is yielded
    when strict, and is yielded as raw bytes otherwise.
    """
    src = _Source(Path(path))
    try:
        wanted = set(topics) if topics is not None else None
        infos = src.topics()
        if wanted is not None:
            absent = sorted(wanted - set(infos))
            if absent:
                raise BagError(f'{path}: topic(s) {absent} not in the bag '
                               f'(has {sorted(infos)})')
        undecodable: set[str] = set()
        ts = None
        if not raw:
            ts = typestore if typestore is not None else make_typestore()
            sel = [i for i in infos.values() if wanted is None or i.name in wanted]
            unknown = _register_bag_types(ts, sel)
            if unknown:
                if strict:
                    raise UnknownTypeError(f'{path}: unknown message type(s), cannot deserialize:'
                                           f' {", ".join(unknown)} (read with raw=True, or '
                                           'strict=False to get these as bytes)')
                warnings.warn(f'{path}: yielding raw bytes for unknown type(s) '
                              f'{", ".join(unknown)}', DamagedBagWarning, stacklevel=2)
                undecodable = {u.split(' ')[0] for u in unknown}
        deser = ts.deserialize_cdr if ts is not None else None
        for topic, msgtype, t, data in src.messages(wanted):
            if raw or topic in undecodable:
                yield BagMessage(topic, msgtype, t, data)
            else:
                assert deser is not None                 # a typestore unless raw
                yield BagMessage(topic, msgtype, t, deser(data, msgtype))
        if src.problems:
            if strict:
                raise DamagedBagError(src.problems)
            warnings.warn('; '.join(src.problems), DamagedBagWarning, stacklevel=2)
    finally:
        src.close()


__all__ = [
    'BagError', 'BagInfo', 'BagMessage', 'BagNotFoundError', 'BagWriter', 'DamagedBagError',
    'DamagedBagWarning', 'TopicInfo', 'TopicSpec', 'UnknownTypeError', 'WriterError',
    'bag_info', 'dump_offered_qos', 'ensure_type', 'make_qos', 'make_typestore',
    'parse_offered_qos', 'read_messages', 'register_package_msgs',
]
