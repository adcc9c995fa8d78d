"""Bad input to the bag, replay and signal handling layers (issue 15): bit rot in any record, cuts, holes, wrong
lengths, a corrupt metadata.yaml, bags without CRCs, and Ctrl-C / SIGTERM at several stages of ``fixego replay``.

Every wait is bounded. No test sleeps for a fixed time to hit a stage: the signal tests replace the estimator or
the front end of the replayed process with stubs that stall after announcing themselves in a marker file, so the
signal always arrives at the stage it is meant for.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import struct
import subprocess
import sys
import textwrap
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import pytest

from fixego_ros.bags.reader import Bag, BagError
from fixego_ros.evaluation.tum import read_tum

BAGS = Path(__file__).resolve().parents[1] / 'bags'
WALK = BAGS / 'walk'
MAGIC = b'\x89MCAP0\r\n'
CHUNK, MESSAGE_INDEX, DATA_END, FOOTER, CHANNEL = 0x06, 0x07, 0x0F, 0x02, 0x04


# ------------------------------------------------------------------------------------------------ helpers
def records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, body length) of every record from the header through the footer (the MCAP framing,
    parsed here independently of the reader under test)."""
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(data):
        op, length = struct.unpack_from('<BQ', data, pos)
        out.append((pos, op, length))
        pos += 9 + length
        if op == FOOTER:
            break
    return out


def of(data: bytes, op: int) -> list[tuple[int, int, int]]:
    return [r for r in records(data) if r[1] == op]


def without_crcs(data: bytearray) -> None:
    """Every CRC field set to 0 ("not computed"), as other writers (rosbags itself) leave them."""
    for pos, _, _ in of(bytes(data), CHUNK):
        struct.pack_into('<I', data, pos + 9 + 24, 0)
    (end_pos, _, _), = of(bytes(data), DATA_END)
    struct.pack_into('<I', data, end_pos + 9, 0)
    struct.pack_into('<I', data, len(data) - len(MAGIC) - 4, 0)


def zstd_rot_without_crcs(data: bytearray) -> None:
    """The probe's case on a CRC-less bag: the second chunk's zstd frame damaged so that zstd rejects it."""
    without_crcs(data)
    pos = of(bytes(data), CHUNK)[1][0]
    (n,) = struct.unpack_from('<I', data, pos + 9 + 28)
    data[pos + 9 + 32 + n + 8] ^= 0x01          # first byte of the zstd frame's magic number


def mcap_of(bag: Path) -> Path:
    (f,) = bag.glob('*.mcap')
    return f


def read_all(path: Path) -> tuple[list[tuple[str, int, bytes]], Bag]:
    bag = Bag(path)
    return [(m.topic, m.log_time_ns, bytes(m.data)) for m in bag.messages()], bag


def damaged_copy(src: Path, dst: Path, edit: Callable[[bytearray], bytes | bytearray | None]) -> Path:
    """A copy of bag directory ``src`` whose .mcap went through ``edit`` (in place, or returning new bytes)."""
    shutil.copytree(src, dst)
    f = mcap_of(dst)
    data = bytearray(f.read_bytes())
    new = edit(data)
    f.write_bytes(bytes(data if new is None else new))
    return dst


def flip(offset: int, bit: int = 0) -> Callable[[bytearray], None]:
    def edit(data: bytearray) -> None:
        data[offset] ^= 1 << bit
    return edit


def chunk_crc_ok(data: bytes, pos: int) -> tuple[int, bool]:
    """(stored CRC, whether it matches) of the chunk record at ``pos`` (zstd or uncompressed)."""
    import zstandard
    _start, _end, size, crc, n = struct.unpack_from('<QQQII', data, pos + 9)
    compression = data[pos + 9 + 32: pos + 9 + 32 + n].decode()
    (csize,) = struct.unpack_from('<Q', data, pos + 9 + 32 + n)
    body = data[pos + 9 + 32 + n + 8: pos + 9 + 32 + n + 8 + csize]
    raw = zstandard.ZstdDecompressor().decompress(body, max_output_size=size) if compression == 'zstd' else body
    return crc, zlib.crc32(raw) == crc


def assert_real_crcs(mcap: Path) -> None:
    """Every chunk, the data section and the summary carry a non-zero CRC that matches the bytes."""
    data = mcap.read_bytes()
    chunks = of(data, CHUNK)
    assert chunks
    for pos, _, _ in chunks:
        crc, ok = chunk_crc_ok(data, pos)
        assert crc != 0 and ok, f'chunk at {pos}: CRC {crc:#x}'
    (end_pos, _, _), = of(data, DATA_END)
    (data_crc,) = struct.unpack_from('<I', data, end_pos + 9)
    assert data_crc != 0 and data_crc == zlib.crc32(data[:end_pos])
    footer_at = len(data) - len(MAGIC) - 29
    summary_start, _, summary_crc = struct.unpack_from('<QQI', data, footer_at + 9)
    assert summary_crc != 0 and summary_crc == zlib.crc32(data[summary_start:footer_at + 25])


@pytest.fixture(scope='module')
def crc_bag(tmp_path_factory) -> Path:
    """3 s of the walk at 320x240, 10 Hz, written by ``fixego sim`` (zstd chunks with CRCs): 31 frames, 5 chunks."""
    from fixego_ros.cli import main as fixego
    out = tmp_path_factory.mktemp('crc') / 'walk_crc'
    assert fixego(['sim', '--trajectory', 'walk', '--duration', '3', '--width', '320', '--height', '240',
                   '--fps', '10', '--no-progress', '--out', str(out)]) == 0
    assert len(of(mcap_of(out).read_bytes(), CHUNK)) >= 4
    return out


@pytest.fixture(scope='module')
def reference(crc_bag) -> list[tuple[str, int, bytes]]:
    msgs, bag = read_all(crc_bag)
    assert bag.report.lines() == [] and len(msgs) == bag.report.expected
    return msgs


# ------------------------------------------------------------------------------------------------ writers
def test_sim_and_recorder_bags_carry_real_crcs(crc_bag, tmp_path):
    """Chunk, data-section and summary CRCs are written (rosbags alone writes 0 = not computed) and every MCAP
    reader that checks them accepts the files."""
    from mcap.reader import make_reader
    from mcap.stream_reader import StreamReader
    from rosbags.rosbag2 import Reader

    from fixego_ros.bags.recorder import BagRecorder

    rec = BagRecorder(tmp_path / 'rec', flush_period_s=0)
    rec.add_topic('/a', 'std_msgs/msg/String', [])
    for i in range(3000):     # ~1.3 MB: more than one chunk
        rec.put('/a', 1000 + i, bytes(12) + bytes(400 + i % 300))
    assert rec.close().ok
    for bag, n in ((crc_bag, None), (tmp_path / 'rec', 3000)):
        assert_real_crcs(mcap_of(bag))
        with mcap_of(bag).open('rb') as fh:
            assert sum(1 for _ in StreamReader(fh, validate_crcs=True).records) > 0
        with mcap_of(bag).open('rb') as fh:
            count = sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages())
        with Reader(bag) as r:        # rosbags checks non-zero chunk CRCs too
            assert sum(1 for _ in r.messages()) == count
        assert n is None or count == n


def test_crc_writer_changes_nothing_but_the_crc_fields(tmp_path):
    """Same input through rosbags' writer and ours: metadata.yaml (topics, QoS, type hashes, counts) identical,
    the .mcap identical except for the CRC fields, so ``ros2 bag info/play`` see the same bag."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from fixego_ros.bags.mcap_storage import bag_writer
    from fixego_ros.sim.bag_writer import _qos

    store = get_typestore(Stores.ROS2_JAZZY)
    String = store.types['std_msgs/msg/String']
    plain_dir, crc_dir = tmp_path / 'plain' / 'bag', tmp_path / 'crc' / 'bag'     # the name is in metadata.yaml
    plain_dir.parent.mkdir()
    crc_dir.parent.mkdir()
    plain = Writer(plain_dir, version=9, storage_plugin=StoragePlugin.MCAP)
    plain.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    for w in (plain, bag_writer(crc_dir)):
        with w:
            w.set_custom_data('k', 'v')
            a = w.add_connection('/a', 'std_msgs/msg/String', typestore=store, offered_qos_profiles=[_qos(True)])
            b = w.add_connection('/b', 'std_msgs/msg/String', typestore=store, offered_qos_profiles=[_qos(False)])
            for i in range(2500):
                w.write(a if i % 3 else b, 10 * i, bytes(store.serialize_cdr(String('x' * (i % 900)),
                                                                             'std_msgs/msg/String')))
    assert (plain_dir / 'metadata.yaml').read_bytes() == (crc_dir / 'metadata.yaml').read_bytes()
    x, y = mcap_of(plain_dir).read_bytes(), mcap_of(crc_dir).read_bytes()
    assert len(x) == len(y)
    crc_fields = [p + 9 + 24 for p, _, _ in of(x, CHUNK)] + [p + 9 for p, _, _ in of(x, DATA_END)]
    crc_fields.append(len(x) - len(MAGIC) - 4)
    assert len(crc_fields) >= 4
    differing = {i for i in range(len(x)) if x[i] != y[i]}
    allowed = {f + k for f in crc_fields for k in range(4)}
    assert differing and differing <= allowed
    assert_real_crcs(mcap_of(crc_dir))


def test_writers_are_deterministic(tmp_path):
    """Same input, same bytes: the simulator's writer, and the recorder fed the same messages (no timed flush).
    (Same directory names under two parents: the name is part of the bag.)"""
    from fixego_ros.bags.recorder import BagRecorder
    from fixego_ros.cli import main as fixego

    for run in ('a', 'b'):
        (tmp_path / run).mkdir()
        assert fixego(['sim', '--trajectory', 'paper', '--steps', '2', '--width', '160', '--height', '120',
                       '--fps', '10', '--texel', '0.006', '--no-progress', '--out', str(tmp_path / run / 'sim')]) == 0
        rec = BagRecorder(tmp_path / run / 'rec', flush_period_s=0)
        rec.add_topic('/a', 'std_msgs/msg/String', [])
        for i in range(2000):
            rec.put('/a', i, bytes(12) + bytes(i % 1000))
        assert rec.close().ok
    for kind in ('sim', 'rec'):
        a, b = tmp_path / 'a' / kind, tmp_path / 'b' / kind
        names = sorted(p.name for p in a.iterdir())
        assert f'{kind}.mcap' in names and names == sorted(p.name for p in b.iterdir())
        for name in names:
            assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_killed_recording_has_checked_chunks(tmp_path):
    """What a SIGKILLed recorder leaves (the file without summary) already carries chunk CRCs: bit rot in it is
    corruption, not a cut."""
    from fixego_ros.bags.recorder import BagRecorder

    rec = BagRecorder(tmp_path / 'bag', flush_period_s=0.05)
    rec.add_topic('/a', 'std_msgs/msg/String', [])
    try:
        for i in range(50):
            rec.put('/a', 1000 + i, bytes(12) + bytes(2000))
        mcap = tmp_path / 'bag' / 'bag.mcap'
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not of(mcap.read_bytes(), CHUNK):
            time.sleep(0.02)
        killed = tmp_path / 'killed'
        killed.mkdir()
        data = mcap.read_bytes()        # a copy as the kill leaves it: chunks, no footer
    finally:
        rec.close()
    chunks = of(data, CHUNK)
    assert chunks, 'no chunk flushed within 30 s'
    for pos, _, _ in chunks:
        crc, ok = chunk_crc_ok(data, pos)
        assert crc != 0 and ok
    (killed / 'bag.mcap').write_bytes(data[:chunks[-1][0] + 9 + chunks[-1][2]])
    msgs, bag = read_all(killed)
    assert msgs and bag.report.truncated and not bag.report.corrupt
    pos, _, length = chunks[0]
    rotten = bytearray(data)
    rotten[pos + 9 + length - 5] ^= 0x10           # in the compressed data of the first chunk
    (killed / 'bag.mcap').write_bytes(bytes(rotten))
    msgs, bag = read_all(killed)
    assert msgs == [] and bag.report.corrupt and 'CRC' in bag.report.corrupt_line()


# ------------------------------------------------------------------------------------------------ reading
def _target(data: bytes, name: str) -> int:
    """Byte offset of a named place to damage in the CRC bag."""
    chunks = of(data, CHUNK)
    pos, _, length = chunks[1]                    # the second chunk: the first one stays readable
    n = struct.unpack_from('<I', data, pos + 9 + 28)[0]
    footer_at = len(data) - len(MAGIC) - 29
    (summary_start,) = struct.unpack_from('<Q', data, footer_at + 9)
    summary_channel = next(p for p, op, _ in records(data) if op == CHANNEL and p > summary_start)
    return {
        'chunk data (raw zstd block)': pos + 9 + length // 2,
        'chunk data end': pos + 9 + length - 3,
        'chunk CRC field': pos + 9 + 24,
        'chunk uncompressed size': pos + 9 + 16,
        'chunk compression name': pos + 9 + 32 + 1,
        'chunk compressed size': pos + 9 + 32 + n + 1,
        'chunk opcode': pos,
        'chunk record length': pos + 1,
        'chunk record length, high byte': pos + 8,
        'message index': of(data, MESSAGE_INDEX)[3][0] + 12,
        'data end CRC': of(data, DATA_END)[0][0] + 9,
        'summary channel': summary_channel + 20,
        'footer summary start': footer_at + 9,
        'closing magic': len(data) - 3,
    }[name]


IN_DATA = ('chunk data (raw zstd block)', 'chunk data end', 'chunk CRC field', 'chunk uncompressed size',
           'chunk compression name', 'chunk compressed size', 'chunk opcode', 'chunk record length',
           'chunk record length, high byte', 'message index')
AFTER_DATA = ('data end CRC', 'summary channel', 'footer summary start', 'closing magic')


@pytest.mark.parametrize('where', IN_DATA + AFTER_DATA)
def test_bit_rot_in_any_record_is_corrupt_and_never_wrong_data(crc_bag, reference, tmp_path, where):
    """One flipped bit anywhere: the bag opens, only intact messages come out (a prefix, nothing from the damaged
    record on), and the report says corrupt, where and what."""
    data = mcap_of(crc_bag).read_bytes()
    bag_dir = damaged_copy(crc_bag, tmp_path / 'rot', flip(_target(data, where), 4))
    msgs, bag = read_all(bag_dir)
    assert msgs == reference[:len(msgs)]
    assert bag.report.corrupt, bag.report.lines()
    line = bag.report.corrupt_line()
    assert line.startswith('corrupt: ') and mcap_of(bag_dir).name in line
    assert line in bag.report.lines()
    if where in IN_DATA:             # reading stops at the damaged record: the messages after it are not given out
        assert 0 < len(msgs) < len(reference)
    else:                            # damage after the data: every message was checked and read
        assert msgs == reference


def test_random_bit_flips_are_always_reported(crc_bag, reference, tmp_path):
    """A seeded sample of single-bit flips over the whole file: never an exception other than BagError (only the
    leading magic), never a wrong message, always reported corrupt (every byte is under some CRC)."""
    data = mcap_of(crc_bag).read_bytes()
    rng = random.Random(15)
    work = damaged_copy(crc_bag, tmp_path / 'rot', lambda d: None)
    for _ in range(40):
        k, bit = rng.randrange(len(data)), rng.randrange(8)
        rotten = bytearray(data)
        rotten[k] ^= 1 << bit
        mcap_of(work).write_bytes(bytes(rotten))
        try:
            msgs, bag = read_all(work)
        except BagError:
            assert k < len(MAGIC)
            continue
        assert msgs == reference[:len(msgs)], (k, bit)
        assert bag.report.corrupt, (k, bit, bag.report.lines())


@pytest.mark.parametrize('fraction', [0.03, 0.3, 0.61, 0.97, 0.9999])
def test_a_cut_file_is_truncated_not_corrupt(crc_bag, reference, tmp_path, fraction):
    """A recording cut short (power loss, a copy that did not finish): every message up to the cut, 'truncated'."""
    bag_dir = damaged_copy(crc_bag, tmp_path / 'cut', lambda d: d[:int(len(d) * fraction)])
    msgs, bag = read_all(bag_dir)
    assert msgs == reference[:len(msgs)]
    assert len(msgs) < len(reference) if fraction < 0.99 else msgs == reference     # 0.9999: cut in the footer
    assert bag.report.truncated and not bag.report.corrupt
    assert any(line.startswith('truncated: ') for line in bag.report.lines())


@pytest.mark.parametrize('edit', ['hole', 'duplicate', 'wrong chunk length'])
def test_holes_and_wrong_lengths_in_a_closed_file_are_corrupt(crc_bag, reference, tmp_path, edit):
    """Bytes missing or repeated in the middle, or a length that points elsewhere: the file still ends with its
    footer, so it was closed and this is corruption, not a cut."""
    data = mcap_of(crc_bag).read_bytes()
    pos, _, length = of(data, CHUNK)[2]
    middle = pos + 9 + length // 2

    def change(d: bytearray) -> bytes:
        if edit == 'hole':
            return bytes(d[:middle] + d[middle + 1000:])
        if edit == 'duplicate':
            return bytes(d[:middle] + d[middle - 1000:])
        struct.pack_into('<Q', d, pos + 1, length - 100)
        return bytes(d)

    msgs, bag = read_all(damaged_copy(crc_bag, tmp_path / edit.replace(' ', '_'), change))
    assert msgs == reference[:len(msgs)] and len(msgs) < len(reference)
    assert bag.report.corrupt


def test_bags_without_crcs_still_read(tmp_path):
    """CRC 0 means "not computed" (MCAP spec): other writers' bags read as before."""
    bag_dir = damaged_copy(WALK, tmp_path / 'nocrc', without_crcs)
    data = mcap_of(bag_dir).read_bytes()
    assert all(struct.unpack_from('<I', data, p + 9 + 24)[0] == 0 for p, _, _ in of(data, CHUNK))
    msgs, bag = read_all(bag_dir)
    assert len(msgs) == 366 and bag.report.lines() == []
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    with Writer(tmp_path / 'plain', version=9, storage_plugin=StoragePlugin.MCAP) as w:    # uncompressed, CRC 0
        c = w.add_connection('/s', 'std_msgs/msg/String', typestore=store)
        for i in range(10):
            text = store.types['std_msgs/msg/String'](f'm{i}')
            w.write(c, i, bytes(store.serialize_cdr(text, 'std_msgs/msg/String')))
    msgs, bag = read_all(tmp_path / 'plain')
    assert len(msgs) == 10 and bag.report.lines() == []


def test_the_original_zstd_error_is_corruption_not_a_traceback(tmp_path):
    """The probe's case: bit rot in the second chunk of a bag without CRCs that zstd rejects."""
    bag_dir = damaged_copy(WALK, tmp_path / 'walk', zstd_rot_without_crcs)
    msgs, bag = read_all(bag_dir)
    assert len(msgs) == 60 and 'zstd' in bag.report.corrupt and bag.report.truncated


@pytest.mark.parametrize('text', [
    b'\xff\xfe\x00garbage',
    b'rosbag2_bagfile_information: [unclosed',
    b'rosbag2_bagfile_information: 5\n',
    b'something_else: {}\n',
    b'rosbag2_bagfile_information: {}\n',
    b'rosbag2_bagfile_information:\n  relative_file_paths: 5\n',
    b'rosbag2_bagfile_information:\n  relative_file_paths: [null]\n',
    b'rosbag2_bagfile_information:\n  relative_file_paths: [walk_crc.mcap]\n  message_count: many\n',
    b'rosbag2_bagfile_information:\n  relative_file_paths: [walk_crc.mcap]\n  custom_data: [1, 2]\n',
    b'rosbag2_bagfile_information:\n  relative_file_paths: [walk_crc.mcap]\n  topics_with_message_count: 7\n',
])
def test_corrupt_metadata_yaml_falls_back_to_the_mcap_file(crc_bag, reference, tmp_path, text):
    """metadata.yaml only repeats what the MCAP file holds: when it is unreadable the bag is read without it."""
    bag_dir = damaged_copy(crc_bag, tmp_path / 'meta', lambda d: None)
    (bag_dir / 'metadata.yaml').write_bytes(text)
    msgs, bag = read_all(bag_dir)
    assert msgs == reference and not bag.report.corrupt and not bag.report.has_metadata
    assert any('metadata.yaml unreadable' in n for n in bag.report.notes), bag.report.notes
    assert '/fixego/right/image_raw' in bag.topics


# ------------------------------------------------------------------------------------------------ replay CLI
def replay_cli(*args: str | Path, timeout: float = 240.0) -> subprocess.CompletedProcess:
    """``fixego replay`` in a child process; a hang fails the test (bounded by ``timeout``)."""
    return subprocess.run([sys.executable, '-m', 'fixego_ros.cli', 'replay', *map(str, args), '--no-progress'],
                          capture_output=True, text=True, timeout=timeout)


def corrupt_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if 'corrupt' in line]


@pytest.mark.parametrize('workers', ['1', '2'])
@pytest.mark.parametrize('source', ['crc bag', 'bag without CRCs'])
def test_replay_of_a_rotten_bag_replays_the_intact_part_and_exits_2(crc_bag, tmp_path, workers, source):
    """Bit rot in the second chunk: the frames before it are replayed and written, one line says corrupt, exit 2,
    no traceback, no hang (with 2 workers the process used to wait for ever on the worker's queue)."""
    if source == 'crc bag':
        data = mcap_of(crc_bag).read_bytes()
        bag_dir = damaged_copy(crc_bag, tmp_path / 'rot', flip(_target(data, 'chunk data (raw zstd block)')))
        full = 31
    else:
        bag_dir = damaged_copy(WALK, tmp_path / 'rot', zstd_rot_without_crcs)
        full = 41
    out = tmp_path / 'est.tum'
    p = replay_cli(bag_dir, '--out', out, '--workers', workers)
    assert p.returncode == 2, p.stderr
    assert 'Traceback' not in p.stderr
    last = p.stderr.strip().splitlines()[-1]
    assert last.startswith(f'fixego replay: {bag_dir}: corrupt: ') and str(out) in last, p.stderr
    assert corrupt_lines(p.stderr) == [last]
    stamps, _ = read_tum(out)
    assert 0 < len(stamps) < full
    assert len(read_tum(tmp_path / 'est.raw.tum')[0]) == len(stamps)


def test_replay_of_a_bag_rotten_from_its_first_chunk_is_one_error_line(crc_bag, tmp_path):
    data = mcap_of(crc_bag).read_bytes()
    pos, _, length = of(data, CHUNK)[0]
    bag_dir = damaged_copy(crc_bag, tmp_path / 'rot', flip(pos + 9 + length // 2))
    p = replay_cli(bag_dir, '--out', tmp_path / 'est.tum', '--workers', '2')
    assert p.returncode == 2 and 'Traceback' not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1 and corrupt_lines(p.stderr), p.stderr
    assert not (tmp_path / 'est.tum').exists()


def test_replay_with_a_damaged_summary_replays_everything_and_exits_2(crc_bag, tmp_path):
    data = mcap_of(crc_bag).read_bytes()
    bag_dir = damaged_copy(crc_bag, tmp_path / 'rot', flip(_target(data, 'summary channel')))
    p = replay_cli(bag_dir, '--out', tmp_path / 'est.tum', '--workers', '1', '--quiet')
    assert p.returncode == 2 and 'Traceback' not in p.stderr
    (line,) = corrupt_lines(p.stderr)
    assert 'summary' in line and 'CRC mismatch' in line
    clean = replay_cli(crc_bag, '--out', tmp_path / 'clean.tum', '--workers', '1', '--quiet')
    assert clean.returncode == 0, clean.stderr
    assert (tmp_path / 'est.tum').read_bytes() == (tmp_path / 'clean.tum').read_bytes()


# ------------------------------------------------------------------------------------------------ signals
STUBS = '''
"""Stages of fixego replay that stall after writing "<stage> <pid>" to $FIXEGO_TEST_MARK."""
import os
import time
from pathlib import Path

from fixego_ros.estimation.smoother import Smoother
from fixego_ros.pipeline.frontend import StereoFrontEnd


def stall(stage):
    Path(os.environ['FIXEGO_TEST_MARK']).write_text(f'{stage} {os.getpid()}')
    while True:
        time.sleep(0.05)


class EstimatorStuckInUpdate(Smoother):
    def update(self, obs):
        stall('estimator')


class EstimatorStuckStarting(Smoother):
    def __init__(self, *args, **kwargs):
        stall('worker start')


class FrontEndStuck(StereoFrontEnd):
    def process(self, stamp, samples):
        stall('frontend')


class EstimatorFailing(Smoother):
    def update(self, obs):
        raise RuntimeError('boom')
'''

PATCHES = {'estimator': 'run.make_backend = fixego_stubs.EstimatorStuckInUpdate',
           'worker start': 'run.make_backend = fixego_stubs.EstimatorStuckStarting',
           'frontend': 'run.StereoFrontEnd = fixego_stubs.FrontEndStuck',
           'failing': 'run.make_backend = fixego_stubs.EstimatorFailing'}


def start_replay(tmp_path: Path, stage: str, workers: str) -> tuple[subprocess.Popen, Path, Path]:
    """``fixego replay`` of the walk bag in its own session with the stub of ``stage``; (process, marker, out)."""
    (tmp_path / 'fixego_stubs.py').write_text(STUBS)
    mark = tmp_path / 'mark'
    out = tmp_path / 'est.tum'
    script = textwrap.dedent(f'''
        import sys
        sys.path.insert(0, {str(tmp_path)!r})
        import fixego_stubs
        from fixego_ros.replay import run
        {PATCHES[stage]}
        from fixego_ros.cli import main
        sys.exit(main(['replay', {str(WALK)!r}, '--out', {str(out)!r}, '--workers', '{workers}', '--no-progress']))
    ''')
    proc = subprocess.Popen([sys.executable, '-c', script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, env={**os.environ, 'FIXEGO_TEST_MARK': str(mark)})
    return proc, mark, out


def reach(proc: subprocess.Popen, mark: Path, stage: str) -> None:
    """Wait (bounded) until the stub of ``stage`` has announced itself; the process must still run."""
    assert wait_for(lambda: (mark.exists() and mark.read_text().startswith(stage)) or proc.poll() is not None,
                    180.0), 'the stage was not reached within 180 s'
    assert proc.poll() is None, proc.communicate()


def end(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


def children(pid: int) -> list[int]:
    out = []
    for d in Path('/proc').iterdir():
        if d.name.isdigit():
            try:
                if int((d / 'stat').read_text().rsplit(')', 1)[1].split()[1]) == pid:
                    out.append(int(d.name))
            except (OSError, IndexError, ValueError):
                continue
    return out


def cmdline(pid: int) -> bytes:
    try:
        return (Path('/proc') / str(pid) / 'cmdline').read_bytes()
    except OSError:
        return b''


def running(pid: int) -> bool:
    """Alive and not a zombie (a zombie has ended; reaping it is its parent's or init's business)."""
    try:
        return (Path('/proc') / str(pid) / 'stat').read_text().rsplit(')', 1)[1].split()[0] not in 'ZX'
    except (OSError, IndexError):
        return False


def wait_for(predicate: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


@pytest.mark.parametrize('stage, workers, sig, to_group', [
    ('estimator', '2', signal.SIGINT, True),        # worker busy, parent waiting for it
    ('worker start', '2', signal.SIGINT, True),     # worker still building its estimator
    ('frontend', '2', signal.SIGINT, True),         # parent busy in the flow, worker idle
    ('frontend', '1', signal.SIGINT, True),
    ('estimator', '2', signal.SIGTERM, False),      # `kill PID`: the parent alone
    ('frontend', '2', signal.SIGTERM, True),
])
def test_signal_ends_replay_promptly_with_one_line(tmp_path, stage, workers, sig, to_group):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) or SIGTERM: exit 128 + signal within
    seconds, one line on stderr, no traceback (neither parent nor worker), the worker process ended, no output."""
    proc, mark, out = start_replay(tmp_path, stage, workers)
    try:
        reach(proc, mark, stage)
        kids = children(proc.pid)
        if workers == '2':
            assert kids, 'no worker process'
        t0 = time.monotonic()
        if to_group:
            os.killpg(proc.pid, sig)
        else:
            os.kill(proc.pid, sig)
        _, stderr = proc.communicate(timeout=60)
        elapsed = time.monotonic() - t0
    finally:
        end(proc)
    assert proc.returncode == 128 + sig, stderr
    assert elapsed < 15.0, f'took {elapsed:.1f} s to stop'        # ~0.2 s measured; generous for a loaded machine
    assert 'Traceback' not in stderr
    assert stderr.strip().splitlines() == [f'fixego replay: interrupted by {signal.Signals(sig).name}'], stderr
    assert wait_for(lambda: not any(running(k) for k in kids), 10.0), [k for k in kids if running(k)]
    assert not out.exists()


def test_a_failing_or_killed_worker_is_one_error_line_not_a_wait(tmp_path):
    """The estimator process raising, or killed from outside: exit 2 with one line, at once (it used to be a
    traceback from the worker and a 120 s wait in the parent)."""
    (tmp_path / 'failing').mkdir()
    proc, _, _ = start_replay(tmp_path / 'failing', 'failing', '2')
    try:
        _, stderr = proc.communicate(timeout=180)
    finally:
        end(proc)
    assert proc.returncode == 2 and 'Traceback' not in stderr
    assert stderr.strip().splitlines() == ['fixego replay: the estimator failed: RuntimeError: boom'], stderr

    (tmp_path / 'killed').mkdir()
    proc, mark, _ = start_replay(tmp_path / 'killed', 'estimator', '2')
    try:
        reach(proc, mark, 'estimator')
        worker = int(mark.read_text().split()[1])
        assert worker != proc.pid
        os.kill(worker, signal.SIGKILL)
        _, stderr = proc.communicate(timeout=60)
    finally:
        end(proc)
    assert proc.returncode == 2 and 'Traceback' not in stderr
    assert stderr.strip().splitlines() == ['fixego replay: the estimator process ended unexpectedly (exit code -9)']


def test_worker_ends_by_itself_when_the_parent_is_killed(tmp_path):
    """SIGKILL leaves no chance to clean up: the worker notices its parent is gone and exits (no orphan)."""
    proc, mark, _ = start_replay(tmp_path, 'frontend', '2')
    try:
        reach(proc, mark, 'frontend')
        assert wait_for(lambda: any(b'spawn_main' in cmdline(k) for k in children(proc.pid)), 60.0)
        workers = [k for k in children(proc.pid) if b'spawn_main' in cmdline(k)]
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
    finally:
        end(proc)
    assert workers and wait_for(lambda: not any(running(k) for k in workers), 30.0)
