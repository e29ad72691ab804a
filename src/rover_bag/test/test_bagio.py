"""bagio without DDS: typestore, splitting writer, reader, and every kind of damaged bag."""
from __future__ import annotations

import json
import random
import shutil
import warnings
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys.stores.ros2_jazzy import builtin_interfaces__msg__Time as Time
from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__Header as Header

from rover_bag.bagio import (
    BagError,
    BagNotFoundError,
    BagWriter,
    DamagedBagError,
    DamagedBagWarning,
    UnknownTypeError,
    bag_info,
    dump_offered_qos,
    make_qos,
    make_typestore,
    parse_offered_qos,
    read_messages,
)

INC = 'coop_msgs/msg/Inclinometer'
IMU = 'sensor_msgs/msg/Imu'
STR = 'std_msgs/msg/String'
SENSOR = [make_qos(reliable=False, transient_local=False, depth=5)]
LATCHED = [make_qos(reliable=True, transient_local=True, depth=1)]
#: every policy off its usual value
ODD_QOS = Qos(QosHistory.KEEP_ALL, 0, QosReliability.BEST_AVAILABLE, QosDurability.SYSTEM_DEFAULT,
              QosTime(1, 2), QosTime(3, 4), QosLiveliness.MANUAL_BY_TOPIC, QosTime(5, 6), True)


@pytest.fixture(scope='module')
def ts():
    return make_typestore()


def inclinometer(ts, i: int):
    cls = ts.types[INC]
    return cls(Header(Time(i // 200, (i % 200) * 5_000_000), 'rover1/inclinometer'),
               0.001 * i, -0.002 * i, 1e-6, 2e-6, 2.5 + 0.01 * i, 2.4, i % 7 == 0)


def write_sample(ts, path: Path, n: int = 600, flush_every: int = 0,
                 **kw) -> list[tuple[str, int, bytes]]:
    """n inclinometer + n/2 imu messages at 200/100 Hz and one latched string; returns what was
    written as (topic, t_ns, cdr) in write order. flush_every: chunk after so many steps."""
    written = []
    imu_cls = ts.types[IMU]
    with BagWriter(path, typestore=ts, **kw) as bag:
        bag.add_topic('/rover1/inclinometer', INC, offered_qos=SENSOR)
        bag.add_topic('/rover1/imu', IMU, offered_qos=SENSOR)
        bag.add_topic('/sim/truth', STR, offered_qos=LATCHED)
        data = ts.serialize_cdr(ts.types[STR]('truth'), STR)
        bag.write('/sim/truth', 1_000, data)
        written.append(('/sim/truth', 1_000, data))
        for i in range(n):
            t = 10_000 + i * 5_000_000
            data = ts.serialize_cdr(inclinometer(ts, i), INC)
            bag.write('/rover1/inclinometer', t, data)
            written.append(('/rover1/inclinometer', t, data))
            if i % 2 == 0:
                imu = imu_cls(Header(Time(0, i), 'imu'), *_imu_fields(ts, i))
                data = ts.serialize_cdr(imu, IMU)
                bag.write('/rover1/imu', t + 1, data)
                written.append(('/rover1/imu', t + 1, data))
            if flush_every and i % flush_every == flush_every - 1:
                bag.flush()
    return written


def _imu_fields(ts, i):
    import numpy as np
    q = ts.types['geometry_msgs/msg/Quaternion'](0.0, 0.0, 0.0, 1.0)
    v = ts.types['geometry_msgs/msg/Vector3']
    cov = np.zeros(9)
    return q, cov, v(0.0, 0.0, 0.1 * i), cov, v(float(i), 0.0, 9.81), cov


def test_coop_msgs_hashes_match_rosidl(ts):
    """The RIHS01 hashes written into metadata equal rosidl's for every coop_msgs message."""
    from ament_index_python.packages import get_package_share_directory
    share = Path(get_package_share_directory('coop_msgs')) / 'msg'
    names = sorted(p.stem for p in share.glob('*.msg'))
    assert len(names) >= 8
    for name in names:
        want = json.loads((share / f'{name}.json').read_text())['type_hashes'][0]
        assert want['type_name'] == f'coop_msgs/msg/{name}'
        assert ts.hash_rihs01(f'coop_msgs/msg/{name}') == want['hash_string'], name
    # and no srv/action types were registered as topics
    assert not [t for t in ts.types if t.startswith('coop_msgs/srv/')]


def test_round_trip_deserialized_and_raw(ts, tmp_path):
    written = write_sample(ts, tmp_path / 'bag')
    got = list(read_messages(tmp_path / 'bag', raw=True))
    assert [(m.topic, m.t_ns, bytes(m.msg)) for m in got] == sorted(written, key=lambda w: w[1])
    incs = [m for m in read_messages(tmp_path / 'bag', ['/rover1/inclinometer'], typestore=ts)]
    assert len(incs) == 600
    assert incs[123].msgtype == INC
    want = inclinometer(ts, 123)
    assert incs[123].msg.roll == want.roll and incs[123].msg.saturated == want.saturated
    assert incs[123].msg.header.frame_id == 'rover1/inclinometer'
    info = bag_info(tmp_path / 'bag')
    assert info.problems == [] and not info.recovered
    assert info.message_count == len(written)
    assert info.topics['/sim/truth'].offered_qos == LATCHED
    assert info.topics['/rover1/imu'].type_hash == ts.hash_rihs01(IMU)


def test_offered_qos_in_rosbag2_format(ts, tmp_path):
    """Offered QoS is written as rosbag2 (metadata version 9) writes it, and read back the same
    from metadata.yaml (by rosbags' reader) and from the MCAP channels (recovery)."""
    profiles = [*LATCHED, ODD_QOS]
    entries = dump_offered_qos(profiles)
    forever = {'sec': 9223372036, 'nsec': 854775807}
    assert entries[0] == {
        'history': 'keep_last', 'depth': 1, 'reliability': 'reliable',
        'durability': 'transient_local', 'deadline': forever, 'lifespan': forever,
        'liveliness': 'automatic', 'liveliness_lease_duration': forever,
        'avoid_ros_namespace_conventions': False}
    assert entries[1]['reliability'] == 'best_available'
    assert entries[1]['liveliness_lease_duration'] == {'sec': 5, 'nsec': 6}
    text = '\n'.join(f'- {json.dumps(e)}' for e in entries)     # JSON is YAML
    assert parse_offered_qos(text) == profiles
    # metadata version 8 wrote the policies as numbers
    v8 = ('- history: 1\n  depth: 5\n  reliability: 2\n  durability: 2\n'
          '  deadline: {sec: 9223372036, nsec: 854775807}\n'
          '  lifespan: {sec: 9223372036, nsec: 854775807}\n  liveliness: 1\n'
          '  liveliness_lease_duration: {sec: 9223372036, nsec: 854775807}\n'
          '  avoid_ros_namespace_conventions: false\n')
    assert parse_offered_qos(v8) == SENSOR
    assert parse_offered_qos('') == []
    for bad, match in [('{a: [', 'not YAML'), ('history: 1', 'not a list'), ('- 3', 'mapping'),
                       (v8.replace('  depth: 5\n', ''), "no 'depth'"),
                       (v8.replace('history: 1', 'history: sometimes'), 'history'),
                       (v8.replace('false', '"no"'), 'not a bool')]:
        with pytest.raises(BagError, match=match):
            parse_offered_qos(bad)
    with BagWriter(tmp_path / 'q', typestore=ts) as bag:
        bag.add_topic('/q', STR, offered_qos=profiles)
        bag.write('/q', 1, ts.serialize_cdr(ts.types[STR]('q'), STR))
    assert 'reliability: best_available\n' in (tmp_path / 'q' / 'metadata.yaml').read_text()
    assert bag_info(tmp_path / 'q').topics['/q'].offered_qos == profiles
    (tmp_path / 'q' / 'metadata.yaml').unlink()
    info = bag_info(tmp_path / 'q')
    assert info.recovered and info.topics['/q'].offered_qos == profiles


def test_split_by_size_and_duration_one_bag(ts, tmp_path):
    written = write_sample(ts, tmp_path / 'size', max_bytes=20_000)
    info = bag_info(tmp_path / 'size')
    names = [f.name for f in info.files]
    assert len(names) >= 3
    assert names == [f'size_{i}.mcap' for i in range(len(names))]
    got = [(m.topic, m.t_ns, bytes(m.msg)) for m in read_messages(tmp_path / 'size', raw=True)]
    assert got == sorted(written, key=lambda w: w[1])
    write_sample(ts, tmp_path / 'dur', max_duration_s=1.0)   # 3 s of data
    files = bag_info(tmp_path / 'dur').files
    assert len(files) == 3
    # every split file is a complete MCAP file a foreign reader opens on its own
    for f in files:
        with f.open('rb') as fh:
            summary = make_reader(fh).get_summary()
        assert summary.statistics.message_count > 0
        assert {c.topic for c in summary.channels.values()} == {
            '/rover1/inclinometer', '/rover1/imu', '/sim/truth'}


def test_split_files_are_merged_in_time_order(ts, tmp_path):
    """A recorder writes in arrival order: a split file can begin with a message older than the
    previous file's last (receive stamps taken on several threads). Read in time order."""
    data = ts.serialize_cdr(ts.types[STR]('x'), STR)
    order = [0, 15, 22, 14, 30, 45, 29, 50]      # files [0 15] [22 14 30] [45 29 50]
    with BagWriter(tmp_path / 'bag', typestore=ts, max_duration_s=20e-9) as bag:
        bag.add_topic('/a', STR, offered_qos=SENSOR)
        bag.add_topic('/b', STR, offered_qos=SENSOR)
        for k, t in enumerate(order):
            bag.write('/a' if k % 2 else '/b', t, data)
    assert len(bag_info(tmp_path / 'bag').files) >= 3
    for topics in (None, ['/a']):
        got = [m.t_ns for m in read_messages(tmp_path / 'bag', topics, raw=True)]
        want = sorted(t for k, t in enumerate(order) if topics is None or k % 2)
        assert got == want


def test_message_compressed_split_bag_is_merged_and_decompressed(ts, tmp_path):
    """A bag of rosbag2's message compression (each message zstd-compressed, as metadata.yaml
    says) split into two files whose times interleave: read merged, decompressed."""
    from ruamel.yaml import YAML
    yaml = YAML(typ='safe')
    stamps = {0: [0, 20, 40], 1: [10, 30, 50]}
    infos = []
    for i, times in stamps.items():
        w = Writer(tmp_path / f'm_{i}', version=9, storage_plugin=StoragePlugin.MCAP)
        w.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
        with w:
            c = w.add_connection('/s', STR, typestore=ts, offered_qos_profiles=SENSOR)
            for t in times:
                w.write(c, t, ts.serialize_cdr(ts.types[STR](f's{t}'), STR))
        infos.append(yaml.load((tmp_path / f'm_{i}' / 'metadata.yaml').read_text())
                     ['rosbag2_bagfile_information'])
    bag = tmp_path / 'm'
    bag.mkdir()
    for i in stamps:
        (tmp_path / f'm_{i}' / f'm_{i}.mcap').replace(bag / f'm_{i}.mcap')
    info = infos[0]
    assert info['compression_mode'].lower() == 'message'
    info['relative_file_paths'] = ['m_0.mcap', 'm_1.mcap']
    info['files'] = [{**f['files'][0], 'path': f'm_{i}.mcap'} for i, f in enumerate(infos)]
    info['message_count'] = 6
    info['topics_with_message_count'][0]['message_count'] = 6
    info['duration'] = {'nanoseconds': 50}
    with (bag / 'metadata.yaml').open('w') as out:
        yaml.dump({'rosbag2_bagfile_information': info}, out)
    got = [(m.t_ns, m.msg.data) for m in read_messages(bag, typestore=ts)]
    assert got == [(t, f's{t}') for t in range(0, 60, 10)]
    assert bag_info(bag).problems == []


def test_foreign_readers_open_the_bag(ts, tmp_path):
    write_sample(ts, tmp_path / 'bag', max_bytes=30_000)
    with AnyReader([tmp_path / 'bag']) as reader:   # default typestore: types from the bag
        conns = [c for c in reader.connections if c.topic == '/rover1/inclinometer']
        msgs = [reader.deserialize(d, c.msgtype) for c, _t, d in reader.messages(conns)]
        assert {c.digest for c in conns} == {ts.hash_rihs01(INC)}
    assert len(msgs) == 600 and msgs[-1].roll == pytest.approx(0.599)
    n = 0
    for f in sorted((tmp_path / 'bag').glob('*.mcap')):
        with f.open('rb') as fh:
            reader = make_reader(fh)
            assert reader.get_header().profile == 'ros2'
            for schema, channel, _message in reader.iter_messages():
                assert schema.encoding == 'ros2msg' and channel.message_encoding == 'cdr'
                n += 1
    assert n == 901
    meta = (tmp_path / 'bag' / 'metadata.yaml').read_text()
    assert 'version: 9' in meta and 'storage_identifier: mcap' in meta
    assert f'type_description_hash: {ts.hash_rihs01(INC)}\n' in meta


def test_missing_bag_and_missing_split_file(ts, tmp_path):
    with pytest.raises(BagNotFoundError, match='does not exist'):
        list(read_messages(tmp_path / 'nope'))
    write_sample(ts, tmp_path / 'bag', max_bytes=20_000)
    (tmp_path / 'bag' / 'bag_1.mcap').unlink()
    with pytest.raises(BagNotFoundError, match=r"missing file\(s\) \['bag_1.mcap'\]"):
        bag_info(tmp_path / 'bag')


def test_no_metadata_reads_what_the_files_allow(ts, tmp_path):
    written = write_sample(ts, tmp_path / 'bag', max_bytes=20_000)
    (tmp_path / 'bag' / 'metadata.yaml').unlink()
    got = []
    with pytest.raises(DamagedBagError, match=r'no metadata\.yaml'):
        for m in read_messages(tmp_path / 'bag', raw=True):
            got.append((m.topic, m.t_ns, bytes(m.msg)))
    assert got == sorted(written, key=lambda w: w[1])      # all of it, before the error
    with pytest.warns(DamagedBagWarning):
        assert len(list(read_messages(tmp_path / 'bag', strict=False))) == len(written)
    info = bag_info(tmp_path / 'bag')
    assert info.recovered and info.topics['/sim/truth'].offered_qos == LATCHED


def write_big(ts, path: Path, n: int = 48, size: int = 100_000,
              **kw) -> list[tuple[str, int, bytes]]:
    """n strings of about `size` bytes: several MiB, so rosbags' writer closes several chunks
    (at 1 MiB each) inside one file; returns (topic, t_ns, cdr) as written."""
    written = []
    with BagWriter(path, typestore=ts, **kw) as bag:
        bag.add_topic('/big', STR, offered_qos=SENSOR)
        for i in range(n):
            text = ' '.join(f'w{(i * 7919 + k * 104729) % 100003}' for k in range(size // 7))
            data = ts.serialize_cdr(ts.types[STR](text), STR)
            bag.write('/big', 1000 + i, data)
            written.append(('/big', 1000 + i, data))
    return written


@pytest.mark.parametrize('seed', [1, 2, 3])
def test_truncated_file_yields_a_prefix(ts, tmp_path, seed):
    written = write_big(ts, tmp_path / 'bag')
    f = tmp_path / 'bag' / 'bag_0.mcap'
    data = f.read_bytes()
    assert len(data) > 3 << 20               # at least three chunks
    cut = random.Random(seed).randrange(len(data) // 2, len(data) - (256 << 10))
    f.write_bytes(data[:cut])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        got = [(m.topic, m.t_ns, bytes(m.msg))
               for m in read_messages(tmp_path / 'bag', raw=True, strict=False)]
    assert any('truncated' in str(w.message) for w in caught)
    assert 0 < len(got) < len(written)
    assert got == written[:len(got)]      # a prefix, never a corrupted message
    with pytest.raises(DamagedBagError, match=rf'bag_0.mcap: truncated at byte \d+ of {cut}'):
        list(read_messages(tmp_path / 'bag', raw=True))


@pytest.mark.parametrize('compression', ['none', 'zstd'])
def test_bad_chunk_keeps_the_chunks_before_it(ts, tmp_path, compression):
    """A chunk that cannot be read (zstd data that do not decompress, a CRC mismatch) ends the
    read of its file, through the index or recovered without metadata.yaml: every message of
    the chunks before it is yielded, none of the bad one's."""
    written = write_big(ts, tmp_path / 'bag', compression=compression)
    f = tmp_path / 'bag' / 'bag_0.mcap'
    with f.open('rb') as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes,
                        key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 3
    bad = chunks[2]
    data = bytearray(f.read_bytes())
    if compression == 'zstd':
        mid = bad.chunk_start_offset + bad.chunk_length // 2
        data[mid:mid + 64] = bytes(64)
    else:   # the chunk's CRC of its records (rosbags leaves it 0: unset): after op, length, 3 u64
        at = bad.chunk_start_offset + 1 + 8 + 3 * 8
        data[at:at + 4] = (12345).to_bytes(4, 'little')
    f.write_bytes(bytes(data))
    kept = sum(1 for _topic, t, _data in written if t <= chunks[1].message_end_time)
    assert 0 < kept < len(written)

    def read(match: str) -> None:
        got = []
        with pytest.raises(DamagedBagError, match=match):
            for m in read_messages(tmp_path / 'bag', raw=True):
                got.append((m.topic, m.t_ns, bytes(m.msg)))
        assert got == written[:kept]

    assert bag_info(tmp_path / 'bag').problems == []    # the index is sound
    read(f'bag: nothing readable after t={written[kept - 1][1]} ns')
    (tmp_path / 'bag' / 'metadata.yaml').unlink()
    read(f'bag_0.mcap: corrupt chunk at byte {bad.chunk_start_offset}: ')


def test_broken_index_reads_every_message(ts, tmp_path):
    """A file whose data are sound but whose summary rosbags cannot use is read whole by the
    recovery read, and the failed indexed read is named."""
    written = write_sample(ts, tmp_path / 'bag')
    f = tmp_path / 'bag' / 'bag_0.mcap'
    data = bytearray(f.read_bytes())
    # the footer's summary start (end magic 8 bytes, before it summary crc 4, summary offset 8)
    data[-28:-20] = (len(data) * 2).to_bytes(8, 'little')
    f.write_bytes(bytes(data))
    with pytest.raises(DamagedBagError, match=r'indexed read failed \(Invalid MCAP summary'):
        got = []
        for m in read_messages(tmp_path / 'bag', raw=True):
            got.append((m.topic, m.t_ns, bytes(m.msg)))
    assert got == sorted(written, key=lambda w: w[1])
    info = bag_info(tmp_path / 'bag')
    assert info.recovered and len(info.problems) == 1
    assert info.topics['/sim/truth'].offered_qos == LATCHED


def test_flush_then_kill_keeps_flushed_messages(ts, tmp_path):
    bag = BagWriter(tmp_path / 'bag', typestore=ts)
    bag.add_topic('/a', STR, offered_qos=SENSOR)
    for i in range(50):
        bag.write('/a', i, ts.serialize_cdr(ts.types[STR](f'm{i}'), STR))
    bag.flush()
    bag.flush()          # nothing new: no empty file
    # a flushed file is finished: complete, indexed, readable by any MCAP reader
    assert sorted(p.name for p in (tmp_path / 'bag').glob('*.mcap')) == ['bag_0.mcap']
    with (tmp_path / 'bag' / 'bag_0.mcap').open('rb') as fh:
        assert make_reader(fh).get_summary().statistics.message_count == 50
    for i in range(50, 80):
        bag.write('/a', i, ts.serialize_cdr(ts.types[STR](f'm{i}'), STR))
    bag.abort()          # what SIGKILL leaves: no metadata, the unflushed file unfinished
    got = [m.msg.data for m in read_messages(tmp_path / 'bag', strict=False)]
    assert got == [f'm{i}' for i in range(50)]
    with pytest.raises(DamagedBagError, match=r'bag_1\.mcap: truncated'):
        list(read_messages(tmp_path / 'bag'))


def test_unknown_type(ts, tmp_path):
    with BagWriter(tmp_path / 'w', typestore=ts) as bag:
        with pytest.raises(UnknownTypeError, match="unknown message type 'nopkg/msg/Nope'"):
            bag.add_topic('/x', 'nopkg/msg/Nope')
        with pytest.raises(UnknownTypeError, match=r'has no Nope\.msg'):
            bag.add_topic('/x', 'coop_msgs/msg/Nope')
        bag.add_topic('/s', STR)
        with pytest.raises(BagError, match='already recorded as std_msgs/msg/String'):
            bag.add_topic('/s', INC)
        with pytest.raises(BagError, match="topic '/t' was not added"):
            bag.write('/t', 0, b'')
    # a bag whose type has no definition anywhere (written without one)
    w = Writer(tmp_path / 'u', version=9, storage_plugin=StoragePlugin.MCAP)
    with w:
        c = w.add_connection('/u', 'nopkg/msg/Nope', msgdef='', rihs01='RIHS01_00')
        w.write(c, 5, b'\x00\x01\x00\x00abcd')
        c2 = w.add_connection('/s', STR, typestore=ts)
        w.write(c2, 6, ts.serialize_cdr(ts.types[STR]('ok'), STR))
    with pytest.raises(UnknownTypeError, match=r'/u \(nopkg/msg/Nope\)'):
        list(read_messages(tmp_path / 'u'))
    assert [m.msg.data for m in read_messages(tmp_path / 'u', ['/s'])] == ['ok']
    with pytest.warns(DamagedBagWarning, match='raw bytes'):
        got = list(read_messages(tmp_path / 'u', strict=False))
    assert got[0].msg == b'\x00\x01\x00\x00abcd' and got[1].msg.data == 'ok'


def test_types_from_the_bag_itself(tmp_path):
    """A bag of a type no typestore knows is read through the definition stored in the bag."""
    from rosbags.typesys import get_types_from_msg
    own = make_typestore()
    own.register(get_types_from_msg('float64 x\nstring label\n', 'vendor_msgs/msg/Thing'))
    with BagWriter(tmp_path / 'b', typestore=own) as bag:
        bag.add_topic('/thing', 'vendor_msgs/msg/Thing')
        bag.write('/thing', 1, own.serialize_cdr(own.types['vendor_msgs/msg/Thing'](2.5, 'k'),
                                                 'vendor_msgs/msg/Thing'))
    (m,) = list(read_messages(tmp_path / 'b'))    # fresh typestore inside
    assert (m.msg.x, m.msg.label) == (2.5, 'k')


def test_writer_refuses_bad_input(ts, tmp_path):
    (tmp_path / 'exists').mkdir()
    with pytest.raises(BagError, match='exists already'):
        BagWriter(tmp_path / 'exists', typestore=ts)
    with pytest.raises(ValueError, match='>= 0'):
        BagWriter(tmp_path / 'neg', typestore=ts, max_bytes=-1)
    with pytest.raises(BagError, match='not in the bag'):
        write_sample(ts, tmp_path / 'ok', n=4)
        list(read_messages(tmp_path / 'ok', ['/nope']))
    bad = tmp_path / 'x.txt'
    bad.write_text('hello')
    with pytest.raises(BagError, match='not a bag directory'):
        bag_info(bad)
    shutil.copy(tmp_path / 'ok' / 'ok_0.mcap', tmp_path / 'single.mcap')
    assert bag_info(tmp_path / 'single.mcap').message_count == 7


def test_zstd_chunks_round_trip_and_recovery(ts, tmp_path):
    written = write_sample(ts, tmp_path / 'z', n=1000, compression='zstd')
    plain = write_sample(ts, tmp_path / 'p', n=1000)
    assert written == plain
    size = lambda p: sum(f.stat().st_size for f in p.glob('*.mcap'))  # noqa: E731
    assert size(tmp_path / 'z') < 0.8 * size(tmp_path / 'p')
    want = sorted(written, key=lambda w: w[1])
    got = [(m.topic, m.t_ns, bytes(m.msg)) for m in read_messages(tmp_path / 'z', raw=True)]
    assert got == want
    with (tmp_path / 'z' / 'z_0.mcap').open('rb') as fh:
        assert sum(1 for _ in make_reader(fh).iter_messages()) == len(written)
    big = write_big(ts, tmp_path / 'zb', compression='zstd')
    (tmp_path / 'zb' / 'metadata.yaml').unlink()
    f = tmp_path / 'zb' / 'zb_0.mcap'
    f.write_bytes(f.read_bytes()[:f.stat().st_size // 2])
    with pytest.warns(DamagedBagWarning):
        got = [(m.topic, m.t_ns, bytes(m.msg))
               for m in read_messages(tmp_path / 'zb', raw=True, strict=False)]
    assert 0 < len(got) < len(big) and got == big[:len(got)]
    with pytest.raises(ValueError, match='compression must be one of'):
        BagWriter(tmp_path / 'bad', typestore=ts, compression='lz4')
