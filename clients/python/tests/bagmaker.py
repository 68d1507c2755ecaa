"""Build ROS bags (rosbag2 MCAP folders, ROS 1 .bag files) from real image files, for the tests.

Writers: rosbags 0.11.9 for rosbag2/MCAP and ROS 1; the PyPI `mcap` package only to re-chunk an MCAP file
with lz4 or a chosen chunk size (rosbags can only write zstd or uncompressed chunks, always ~1 MiB);
Debian's python3-rosbag (the ROS 1 reference writer) through /usr/bin/python3.
`frames` is always a list of (image_path, stamp_seconds). Usage: python bagmaker.py OUT_DIR
"""
from __future__ import annotations

import base64
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

import numpy as np
from PIL import Image
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.base import Nodetype
from ruamel.yaml import YAML

TS1, TS2 = get_typestore(Stores.ROS1_NOETIC), get_typestore(Stores.ROS2_JAZZY)
MODES = {'rgb8': 'RGB', 'bgr8': 'RGB', 'rgba8': 'RGBA', 'bgra8': 'RGBA', 'mono8': 'L', 'mono16': 'L'}


def raw_pixels(path, encoding='rgb8', pad=0, bigendian=False):
    """(height, width, step, data) of sensor_msgs/Image for `path` decoded into `encoding`."""
    im = Image.open(path)
    if encoding == 'mono16':
        # a 16-bit PNG keeps its values; 8-bit grey is scaled *257 so 255 maps to 65535
        a = np.asarray(im, np.uint16) if im.mode.startswith('I') else np.asarray(im.convert('L'), np.uint16) * 257
        a = a.astype('>u2' if bigendian else '<u2')
    else:
        a = np.asarray(im.convert(MODES[encoding]))
        if encoding.startswith('bgr'):
            a = a[..., [2, 1, 0, 3][:a.shape[2]]]
    h, w = a.shape[:2]
    rows = np.ascontiguousarray(a).reshape(h, -1).view(np.uint8)
    if pad:  # nonzero garbage after each row, so a reader that ignores `step` shows visibly wrong pixels
        rows = np.hstack([rows, np.random.default_rng(h * w).integers(1, 256, (h, pad), dtype=np.uint8)])
    return h, w, rows.shape[1], rows.tobytes()


def messages(frames, topic, kind, encoding=None, pad=0, bigendian=False, decoys=True):
    """[(topic, msgtype, log_time_ns, fields)] sorted by time; kind None gives only the decoys."""
    cam = topic.removesuffix('/compressed').rsplit('/', 1)[0]  # /robot1/cam/image_raw[/compressed] -> /robot1/cam
    robot = '/' + topic.split('/')[1]  # -> /robot1
    out = []
    for i, (path, stamp) in enumerate(frames):
        t = round(stamp * 1e9)
        hdr = {'seq': i, 'stamp': t, 'frame_id': 'cam'}  # seq is dropped for ROS 2 (no such field)
        if kind == 'compressed':
            fmt = encoding or ('png' if str(path).lower().endswith('.png') else 'jpeg')
            out.append((topic, 'sensor_msgs/msg/CompressedImage', t,
                        {'header': hdr, 'format': fmt, 'data': pathlib.Path(path).read_bytes()}))
        elif kind == 'raw':
            enc = encoding or 'rgb8'
            h, w, step, data = raw_pixels(path, enc, pad, bigendian)
            out.append((topic, 'sensor_msgs/msg/Image', t, {'header': hdr, 'height': h, 'width': w, 'encoding': enc,
                        'is_bigendian': int(bigendian), 'step': step, 'data': data}))
        elif kind is not None:
            raise ValueError(f'kind {kind!r}: compressed, raw or None')
        if not decoys:
            continue
        # decoys a reader must skip: IMU (no namespace), camera_info beside the image topic, a String
        w, h = Image.open(path).size
        out.append((cam + '/camera_info', 'sensor_msgs/msg/CameraInfo', t, {
            'header': hdr, 'width': w, 'height': h, 'distortion_model': 'plumb_bob', 'd': [0.0] * 5,
            'k': [w / 2, 0, w / 2, 0, w / 2, h / 2, 0, 0, 1]}))
        out.append((robot + '/status', 'std_msgs/msg/String', t + 1, {'data': f'frame {i} {pathlib.Path(path).name}'}))
        for k in range(3):
            out.append(('/imu', 'sensor_msgs/msg/Imu', t + 2 + k * 3_000_000, {
                'header': {'seq': 3 * i + k, 'stamp': t + 2 + k * 3_000_000, 'frame_id': 'imu'},
                'orientation': {'w': 1.0}, 'linear_acceleration': {'z': 9.81}}))
    return sorted(out, key=lambda m: m[2])


def build(ts, msgtype, vals):
    """A rosbags message object: fields from `vals` (ROS 1 upper-case names accept lower case), rest zero."""
    kw = {}
    for name, (nt, arg) in ts.fielddefs[msgtype][1]:
        v = vals.get(name, vals.get(name.lower()))
        if nt == Nodetype.NAME and arg == 'builtin_interfaces/msg/Time':
            kw[name] = ts.types[arg](sec=(v or 0) // 10**9, nanosec=(v or 0) % 10**9)
        elif nt == Nodetype.NAME:
            kw[name] = build(ts, arg, v or {})
        elif nt == Nodetype.BASE:
            kw[name] = v if v is not None else ('' if arg[0] == 'string' else 0)
        elif arg[0][0] == Nodetype.BASE:  # fixed array or sequence of a base type -> numpy array
            dt = np.dtype({'byte': 'u1', 'char': 'u1', 'bool': '?'}.get(arg[0][1][0], arg[0][1][0]))
            if isinstance(v, bytes):
                kw[name] = np.frombuffer(v, dt)
            else:
                kw[name] = np.array(v, dt) if v is not None else np.zeros(arg[1], dt)
        else:  # sequence of messages (e.g. RegionOfInterest lists): not needed here
            kw[name] = []
    return ts.types[msgtype](**kw)


def _write_rosbag2(folder, msgs, compression, chunk_size):
    """One rosbag2 MCAP folder via rosbags; lz4 or a chunk size means re-chunking with the mcap package."""
    folder = pathlib.Path(folder)
    native = compression in ('zstd', 'none') and chunk_size is None
    bag = Ros2Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP)
    if native and compression == 'zstd':
        # STORAGE mode = MCAP chunk compression (zstd); metadata.yaml keeps compression_mode ''
        bag.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with bag:
        conns = {}
        for topic, msgtype, t, fields in msgs:
            if topic not in conns:
                conns[topic] = bag.add_connection(topic, msgtype, typestore=TS2)
            bag.write(conns[topic], t, TS2.serialize_cdr(build(TS2, msgtype, fields), msgtype))
    if not native:
        rechunk(folder / f'{folder.name}.mcap', compression, chunk_size or 1 << 20)
    return folder


def rechunk(path, compression, chunk_size):
    """Rewrite an MCAP file in place with chunk compression 'zstd'|'lz4'|'none' and `chunk_size` bytes."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer
    path = pathlib.Path(path)
    tmp = path.with_suffix('.tmp')
    with path.open('rb') as f, tmp.open('wb') as g:
        r = make_reader(f)
        summ, head = r.get_summary(), r.get_header()
        w = Writer(g, chunk_size=chunk_size, compression=CompressionType[compression.upper()])
        w.start(head.profile, head.library)
        sids = {s.id: w.register_schema(s.name, s.encoding, s.data) for s in summ.schemas.values()}
        cids = {c.id: w.register_channel(c.topic, c.message_encoding, sids[c.schema_id], c.metadata)
                for c in summ.channels.values()}
        for m in r.iter_metadata():  # rosbag2's 'rosbag2' record with serialized_metadata
            w.add_metadata(m.name, m.metadata)
        for _, ch, msg in r.iter_messages(log_time_order=True):
            w.add_message(cids[ch.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
        w.finish()
    tmp.replace(path)


def write_mcap(out_path, frames, topic, kind, encoding=None, pad=0, compression='zstd', decoys=True,
               chunk_size=None, bigendian=False):
    """A rosbag2 folder (metadata.yaml + <name>.mcap); compression = MCAP chunk compression zstd|lz4|none."""
    return _write_rosbag2(out_path, messages(frames, topic, kind, encoding, pad, bigendian, decoys),
                          compression, chunk_size)


def write_split_mcap(out_dir, frames, topic, kind, parts=2, encoding=None, pad=0, compression='zstd',
                     decoys=True, chunk_size=None, bigendian=False):
    """A split rosbag2 folder: <name>_0.mcap .. <name>_{parts-1}.mcap of consecutive frames, one metadata.yaml."""
    out_dir = pathlib.Path(out_dir)
    assert 1 <= parts <= len(frames), 'every part needs at least one frame'
    msgs = messages(frames, topic, kind, encoding, pad, bigendian, decoys)
    cuts = [round(len(frames) * k / parts) for k in range(1, parts)]  # first frame index of parts 1..
    starts = [round(frames[c][1] * 1e9) for c in cuts]
    groups = [[m for m in msgs if sum(m[2] >= s for s in starts) == k] for k in range(parts)]
    out_dir.mkdir(parents=True)
    yaml = YAML(typ='safe')
    yaml.default_flow_style = False
    metas = []
    with tempfile.TemporaryDirectory() as tmp:
        for k, group in enumerate(groups):
            part = _write_rosbag2(pathlib.Path(tmp) / f'{out_dir.name}_{k}', group, compression, chunk_size)
            shutil.move(part / f'{part.name}.mcap', out_dir / f'{part.name}.mcap')
            metas.append(yaml.load(part / 'metadata.yaml')['rosbag2_bagfile_information'])
    info = metas[0]  # same layout as rosbag2's own split bags: totals at the top, one `files` entry per file
    info['relative_file_paths'] = [m['relative_file_paths'][0] for m in metas]
    info['files'] = [m['files'][0] for m in metas]
    start = min(m['starting_time']['nanoseconds_since_epoch'] for m in metas)
    end = max(m['starting_time']['nanoseconds_since_epoch'] + m['duration']['nanoseconds'] for m in metas)
    info['starting_time'], info['duration'] = {'nanoseconds_since_epoch': start}, {'nanoseconds': end - start}
    info['message_count'] = sum(m['message_count'] for m in metas)
    topics = {}
    for m in metas:
        for tm in m['topics_with_message_count']:
            topics.setdefault(tm['topic_metadata']['name'], dict(tm, message_count=0))['message_count'] += tm['message_count']
    info['topics_with_message_count'] = list(topics.values())
    with (out_dir / 'metadata.yaml').open('w') as f:
        yaml.dump({'rosbag2_bagfile_information': info}, f)
    return out_dir


def write_ros1_rosbags(out_path, frames, topic, kind, encoding=None, pad=0, compression=None, decoys=True,
                       bigendian=False):
    """A ROS 1 .bag via rosbags.rosbag1.Writer; compression None|'bz2'|'lz4' (chunk compression)."""
    bag = Ros1Writer(out_path)
    if compression:
        bag.set_compression(Ros1Writer.CompressionFormat[compression.upper()])
    with bag:
        conns = {}
        for topic_, msgtype, t, fields in messages(frames, topic, kind, encoding, pad, bigendian, decoys):
            if topic_ not in conns:
                conns[topic_] = bag.add_connection(topic_, msgtype, typestore=TS1)
            bag.write(conns[topic_], t, TS1.serialize_ros1(build(TS1, msgtype, fields), msgtype))
    return out_path


# Runs under Debian's /usr/bin/python3 (python3-rosbag, python3-sensor-msgs): genpy messages from a JSON spec.
DEBIAN_SCRIPT = r'''
import base64, importlib, json, sys
import genpy, rosbag
def fill(msg, vals):
    for k, v in vals.items():
        k = k if hasattr(msg, k) else k.upper()  # CameraInfo: ROS 1 says D/K, ROS 2 d/k
        if k == 'stamp':
            setattr(msg, k, genpy.Time(v // 10**9, v % 10**9))
        elif isinstance(v, dict) and 'b64' in v:
            setattr(msg, k, base64.b64decode(v['b64']))
        elif isinstance(v, dict):
            fill(getattr(msg, k), v)
        else:
            setattr(msg, k, v)
spec = json.load(open(sys.argv[1]))
with rosbag.Bag(spec['out'], 'w', compression=spec['compression']) as bag:
    for topic, msgtype, t, fields in spec['msgs']:
        pkg, _, name = msgtype.split('/')
        msg = getattr(importlib.import_module(pkg + '.msg'), name)()
        fill(msg, fields)
        bag.write(topic, msg, genpy.Time(t // 10**9, t % 10**9))
'''


def write_ros1_debian(out_path, frames, topic, kind, encoding=None, pad=0, compression='lz4', decoys=True,
                      bigendian=False, python='/usr/bin/python3'):
    """A ROS 1 .bag by Debian's python3-rosbag (reference implementation); compression 'none'|'bz2'|'lz4'."""
    def enc(v):
        return {'b64': base64.b64encode(v).decode()} if isinstance(v, bytes) else \
            {k: enc(x) for k, x in v.items()} if isinstance(v, dict) else v
    msgs = [[tp, mt, t, enc(f)] for tp, mt, t, f in messages(frames, topic, kind, encoding, pad, bigendian, decoys)]
    with tempfile.TemporaryDirectory() as tmp:
        spec = pathlib.Path(tmp) / 'spec.json'
        spec.write_text(json.dumps({'out': str(out_path), 'compression': compression or 'none', 'msgs': msgs}))
        script = pathlib.Path(tmp) / 'write.py'
        script.write_text(DEBIAN_SCRIPT)
        run = subprocess.run([python, str(script), str(spec)], capture_output=True, text=True)
        if run.returncode:
            raise RuntimeError(f'{python} (apt-get install python3-rosbag python3-sensor-msgs) failed: {run.stderr}')
    return out_path


def debian_rosbag_available(python='/usr/bin/python3'):
    """Whether write_ros1_debian can run here (for pytest skips)."""
    return subprocess.run([python, '-c', 'import rosbag, sensor_msgs.msg'], capture_output=True).returncode == 0


def write_imageless(out_path, frames, topic, fmt='mcap'):
    """A bag with only the decoy topics (no image topic at all): fmt 'mcap' or 'ros1'."""
    if fmt == 'mcap':
        return write_mcap(out_path, frames, topic, None)
    return write_ros1_rosbags(out_path, frames, topic, None)


def truncate(path_in, path_out, frac):
    """The first `frac` of a file (a recording cut off mid-write: no MCAP footer / no ROS 1 index)."""
    data = pathlib.Path(path_in).read_bytes()
    pathlib.Path(path_out).write_bytes(data[:int(len(data) * frac)])
    return path_out


def corrupt(path_in, path_out, seed, nbytes=64):
    """A copy with `nbytes` bytes in the middle third flipped (XOR 0xFF) at seeded positions."""
    data = bytearray(pathlib.Path(path_in).read_bytes())
    n = len(data)
    for i in np.random.default_rng(seed).integers(n // 3, 2 * n // 3, nbytes):
        data[i] ^= 0xFF
    pathlib.Path(path_out).write_bytes(bytes(data))
    return path_out


def mcap_info(path):
    """{'chunk_compression', 'schemas': [(name, encoding)], 'message_encodings', 'messages'} of one .mcap."""
    from mcap.reader import make_reader
    with open(path, 'rb') as f:
        s = make_reader(f).get_summary()
    return {'chunk_compression': sorted({c.compression or 'none' for c in s.chunk_indexes}),
            'schemas': sorted({(x.name, x.encoding) for x in s.schemas.values()}),
            'message_encodings': sorted({c.message_encoding for c in s.channels.values()}),
            'messages': s.statistics.message_count}


if __name__ == '__main__':
    out = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else 'bags')
    out.mkdir(parents=True, exist_ok=True)
    data = pathlib.Path(os.environ.get('LOOPD_SHARED_DATA') or pathlib.Path(__file__).resolve().parents[4] / 'shared/data')
    corridor = [(p, 1700000000.0 + i * 0.5) for i, p in enumerate(sorted((data / 'corridor/ref').glob('*.jpg'))[:6])]
    desk = [(data / f'slambook2-ch11/{i}.png', 1700000100.0 + i) for i in range(1, 4)]
    img = '/robot1/cam/image_raw'
    write_mcap(out / 'mcap_jpeg_zstd', corridor, img + '/compressed', 'compressed')
    write_mcap(out / 'mcap_png_lz4', desk, img + '/compressed', 'compressed', compression='lz4')
    write_mcap(out / 'mcap_bgr8_pad_none', corridor, img, 'raw', 'bgr8', pad=3, compression='none')
    write_mcap(out / 'mcap_mono16be_lz4', corridor, img, 'raw', 'mono16', compression='lz4', bigendian=True,
               chunk_size=32 << 10)
    write_split_mcap(out / 'mcap_split', corridor, '/robot2/cam/image_raw', 'raw', parts=3, encoding='rgba8')
    write_imageless(out / 'mcap_no_images', corridor, img)
    write_ros1_rosbags(out / 'ros1_rosbags_lz4.bag', corridor, img, 'raw', 'mono8', compression='lz4')
    write_ros1_rosbags(out / 'ros1_rosbags_bz2.bag', corridor, img + '/compressed', 'compressed', compression='bz2')
    write_ros1_debian(out / 'ros1_debian_lz4.bag', corridor, img, 'raw', 'bgra8', pad=2, compression='lz4')
    write_ros1_debian(out / 'ros1_debian_jpeg.bag', corridor, img + '/compressed', 'compressed', compression='none')
    truncate(out / 'ros1_rosbags_lz4.bag', out / 'ros1_truncated.bag', 0.6)
    truncate(out / 'mcap_jpeg_zstd/mcap_jpeg_zstd.mcap', out / 'truncated.mcap', 0.6)
    corrupt(out / 'mcap_mono16be_lz4/mcap_mono16be_lz4.mcap', out / 'corrupt.mcap', seed=1)
    corrupt(out / 'ros1_debian_lz4.bag', out / 'ros1_corrupt.bag', seed=1)
    for p in sorted(out.rglob('*')):
        if p.is_file():
            info = mcap_info(p) if p.suffix == '.mcap' and p.parent != out else ''
            print(f'{p.stat().st_size:>9}  {p.relative_to(out)}  {info}')
