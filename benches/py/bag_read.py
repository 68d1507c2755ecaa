"""The peer for benches/bags.rs: what a user would otherwise run to take a bag's images out,
rosbags (PyPI 0.11.9) reading and deserialising each image message, raw images turned into PNG
bytes with Pillow (zlib level 1), compressed ones taken as recorded.

  bag_read.py make OUT_DIR        writes the bench's bags (clients/python/tests/bagmaker.py)
  bag_read.py read BAG TOPIC REPS prints {"frames": N, "seconds": [..]} (one per repetition)
"""
import io
import json
import pathlib
import sys
import time

import numpy as np
from PIL import Image
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

ROOT = pathlib.Path(__file__).resolve().parents[2]
DATA = ROOT.parent / "shared/data"
CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1, "rgba8": 4, "bgra8": 4}


def make(out):
    sys.path.insert(0, str(ROOT / "clients/python/tests"))
    import bagmaker
    out = pathlib.Path(out)
    corridor = [(p, 1e9 + 0.1 * i) for i, p in enumerate(sorted((DATA / "corridor/ref").glob("*.jpg"))
                                                           + sorted((DATA / "corridor/query").glob("*.jpg")))]
    desk = [(DATA / f"slambook2-ch11/{1 + i % 10}.png", 1e9 + i) for i in range(100)]
    cam = "/robot1/cam/image_raw"
    bagmaker.write_mcap(out / "corridor-jpeg-zstd", corridor, cam + "/compressed", "compressed")
    bagmaker.write_ros1_rosbags(out / "corridor-jpeg.bag", corridor, cam + "/compressed", "compressed")
    bagmaker.write_mcap(out / "desk-rgb8-zstd", desk, cam, "raw", "rgb8")
    bagmaker.write_ros1_rosbags(out / "desk-rgb8-lz4.bag", desk, cam, "raw", "rgb8", compression="lz4")


def png(msg):
    channels = CHANNELS[msg.encoding]
    rows = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.step)[:, :msg.width * channels]
    a = rows.reshape(msg.height, msg.width, channels)
    if msg.encoding.startswith("bgr"):
        a = a[..., [2, 1, 0, 3][:channels]]
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray((a[..., :3] if channels == 4 else a).squeeze())).save(buf, "PNG", compress_level=1)
    return buf.getvalue()


def read(bag, topic):
    frames = 0
    with AnyReader([pathlib.Path(bag)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as r:
        for conn, _, raw in r.messages(connections=[c for c in r.connections if c.topic == topic]):
            msg = r.deserialize(raw, conn.msgtype)
            image = bytes(msg.data) if conn.msgtype.endswith("CompressedImage") else png(msg)
            frames += bool(image)
    return frames


if __name__ == "__main__":
    if sys.argv[1] == "make":
        make(sys.argv[2])
    else:
        bag, topic, reps = sys.argv[2], sys.argv[3], int(sys.argv[4])
        seconds = []
        for _ in range(reps):
            t = time.perf_counter()
            frames = read(bag, topic)
            seconds.append(time.perf_counter() - t)
        print(json.dumps({"frames": frames, "seconds": seconds}))
