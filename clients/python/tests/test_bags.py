"""Bags in: rosbag2 MCAP and ROS 1 bags built here from real frames (bagmaker.py: PyPI rosbags, the
PyPI mcap writer for lz4 chunks, Debian's python3-rosbag) go through the sequence job of a real
`loopd serve` (TLS, tenant key), by HTTP upload and by `loopd ingest`. A bag job must give exactly
the frames and loops of the folder job on the same pictures; corridor's R@100P from the bag's
session must equal `loopd eval`'s; broken bags are 400s that say what is wrong."""
from __future__ import annotations

import io
import json
import pathlib
import subprocess
import tarfile
import time
import urllib.error
import urllib.parse
import urllib.request

import bagmaker
import pytest
from conftest import BIN, DATA
from PIL import Image

from loopd_client import Client, query_options

CORRIDOR_REF = sorted((DATA / "corridor/ref").glob("*.jpg"))
CORRIDOR_QUERY = sorted((DATA / "corridor/query").glob("*.jpg"))
DESK = [DATA / f"slambook2-ch11/{i}.png" for i in range(1, 11)]
T0 = 1_700_000_000.0


@pytest.fixture(scope="module")
def key(server):
    k = server.tenant("bags")
    path = server.root / "bags.key"
    path.write_text(k)
    return k


def call(server, key, method, path, body=None, query=None, ctype="application/json"):
    """(status, JSON answer) of one HTTP call with the tenant's key."""
    url = f"https://127.0.0.1:{server.http_port}{path}"
    if query:
        url += "?" + urllib.parse.urlencode(query)
    data = json.dumps(body).encode() if isinstance(body, dict) else body
    req = urllib.request.Request(url, method=method, data=data,
                                 headers={"Authorization": f"Bearer {key}", "Content-Type": ctype})
    try:
        with urllib.request.urlopen(req, context=server.ssl, timeout=300) as r:
            return r.status, json.load(r)
    except urllib.error.HTTPError as e:
        return e.code, json.load(e)


def session(server, key, name):
    status, answer = call(server, key, "POST", "/v1/sessions", {"id": name, "storage": "f32"})
    assert status == 201, answer


def wait_job(server, key, job_id):
    while True:
        status, job = call(server, key, "GET", f"/v1/jobs/{job_id}")
        assert status == 200, job
        if job["state"] != "running":
            return job
        time.sleep(0.2)


def upload(server, key, name, body, **query):
    """A sequence job on a new session from one body (tar or bag); its finished status."""
    session(server, key, name)
    status, answer = call(server, key, "POST", f"/v1/sessions/{name}/sequences", body,
                          {k: str(v) for k, v in query.items()}, "application/octet-stream")
    assert status == 202, answer
    return wait_job(server, key, answer["job_id"])


def folder_job(server, key, name, files):
    """The folder job: the same pictures as a tar, in the given order."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as t:
        for i, f in enumerate(files):
            t.add(f, arcname=f"{i:05d}{f.suffix}")
    job = upload(server, key, name, buf.getvalue())
    assert job["state"] == "done" and not job["errors"], job
    return job


def ingest(server, *args):
    """`loopd ingest` against the test server; its finished job (JSON)."""
    out = subprocess.run([str(BIN), "ingest", *map(str, args), "--server", f"https://127.0.0.1:{server.http_port}",
                          "--ca", str(server.ca), "--key-file", str(server.root / "bags.key"), "--json"],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def loops(job):
    return [(l["query_index"], l["match_index"]) for l in job["loops"]]


def same_loops(got, want):
    """Same frames, same loops (pairs exactly; scores up to batching's rounding)."""
    assert (got["state"], got["total"], got["done"], got["errors"]) == ("done", want["total"], want["done"], [])
    assert loops(got) == loops(want)
    for a, b in zip(got["loops"], want["loops"]):
        assert abs(a["score"] - b["score"]) < 1e-4, (a, b)


def one_file(bag):
    """The .mcap inside a rosbag2 folder (bagmaker writes folders), or the .bag itself."""
    return next(bag.glob("*.mcap")) if bag.is_dir() else bag


def r_at_100p(results, truth):
    """docs/evaluation.md's recall at 100% precision (as src/eval/metrics.rs: ties, wrong first)."""
    accepted = sorted(((s, r in truth[q]) for q, (r, s) in results.items()), key=lambda a: (-a[0], a[1]))
    tp = fp = i = 0
    best = 0.0
    while i < len(accepted):
        score = accepted[i][0]
        while i < len(accepted) and accepted[i][0] == score:
            tp, fp = tp + accepted[i][1], fp + (not accepted[i][1])
            i += 1
        if fp == 0:
            best = tp / len(truth)
    return best


def test_corridor_bag_session_gives_loopd_evals_r_at_100p(server, key, tmp_path):
    frames = [(p, T0 + 0.1 * i) for i, p in enumerate(CORRIDOR_REF + CORRIDOR_QUERY)]
    topic = "/mapper/cam/image_raw/compressed"
    bag = bagmaker.write_mcap(tmp_path / "corridor", frames, topic, "compressed")
    # The folder job on the same pictures is the desk test's reference; here `loopd eval` is.
    session(server, key, "corridor-bag")
    got = ingest(server, bag, "--session", "corridor-bag")
    assert (got["state"], got["total"], got["done"], got["errors"]) == ("done", 222, 222, []), got
    # Frame order, stamps and robot come from the bag.
    for i in (0, 110, 111, 221):
        status, f = call(server, key, "GET", f"/v1/sessions/corridor-bag/frames/{i}")
        assert status == 200, f
        assert (f["metadata"]["name"], f["robot_id"]) == (f"{topic}#{i}", "mapper"), f
        assert abs(f["timestamp"] - frames[i][1]) < 1e-6, f

    # R@100P through the server on the bag's session equals `loopd eval` on the folders.
    client = Client(server.grpc, ca=server.ca, key=key)
    n = len(CORRIDOR_REF)
    results = {}
    for q in range(n):
        m = client.query("corridor-bag", "mapper", frame_id=n + q, options=query_options(
            k=1, scope="all", frame_id_from=0, frame_id_to=n - 1, verify=False, exclude_last_frames=0))
        results[q] = (m[0].frame_id, m[0].score)
    truth = {}
    for line in (DATA / "corridor/gt.csv").read_text().splitlines()[1:]:
        q, refs = line.split(",")
        truth[int(q)] = {int(r) for r in refs.split()}
    out = subprocess.run([str(BIN), "eval", "--device", "cpu", "--sequence", DATA / "corridor/ref",
                          "--query-sequence", DATA / "corridor/query", "--gt", DATA / "corridor/gt.csv",
                          "--cache-dir", tmp_path / "cache", "--json"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert r_at_100p(results, truth) == pytest.approx(report["recall_at_100_precision"], abs=1e-9), report
    print(f"corridor R@100P: bag session {r_at_100p(results, truth):.4f}, loopd eval "
          f"{report['recall_at_100_precision']:.4f}")


def test_raw_encodings_and_both_ros1_writers_give_the_folder_jobs_loops(server, key, tmp_path):
    """Raw pixels go through PNG losslessly, so desk PNGs in a bag in any encoding give exactly the
    loops of the same PNGs in a folder (mono encodings: of the grey PNGs)."""
    frames = [(p, T0 + i) for i, p in enumerate(DESK)]
    grey = []
    for p in DESK:
        g = tmp_path / f"grey-{p.name}"
        Image.open(p).convert("L").save(g)
        grey.append(g)
    want = {"rgb": folder_job(server, key, "desk-rgb", DESK), "grey": folder_job(server, key, "desk-grey", grey)}
    # The desk loop (10.png -> 1.png) is among them.
    assert (9, 0) in loops(want["rgb"]), want["rgb"]["loops"]
    img, cmp = "/robot1/cam/image_raw", "/robot1/cam/image_raw/compressed"
    cases = {
        "mcap rgb8 zstd": lambda p: bagmaker.write_mcap(p, frames, img, "raw", "rgb8"),
        "mcap bgr8 padded, uncompressed": lambda p: bagmaker.write_mcap(p, frames, img, "raw", "bgr8", pad=3,
                                                                         compression="none"),
        "mcap rgba8 lz4 small chunks": lambda p: bagmaker.write_mcap(p, frames, img, "raw", "rgba8",
                                                                      compression="lz4", chunk_size=64 << 10),
        "mcap bgra8 padded zstd": lambda p: bagmaker.write_mcap(p, frames, img, "raw", "bgra8", pad=5),
        "mcap mono8 zstd": lambda p: bagmaker.write_mcap(p, frames, img, "raw", "mono8"),
        "mcap mono16 lz4": lambda p: bagmaker.write_mcap(p, frames, img, "raw", "mono16", compression="lz4"),
        "mcap mono16 big-endian padded": lambda p: bagmaker.write_mcap(p, frames, img, "raw", "mono16", pad=2,
                                                                        bigendian=True, compression="none"),
        "mcap png compressed lz4": lambda p: bagmaker.write_mcap(p, frames, cmp, "compressed", compression="lz4"),
        "ros1 rosbags rgb8 bz2": lambda p: bagmaker.write_ros1_rosbags(p, frames, img, "raw", "rgb8",
                                                                       compression="bz2"),
        "ros1 rosbags mono8 lz4": lambda p: bagmaker.write_ros1_rosbags(p, frames, img, "raw", "mono8",
                                                                        compression="lz4"),
        "ros1 debian bgra8 padded lz4": lambda p: bagmaker.write_ros1_debian(p, frames, img, "raw", "bgra8", pad=2,
                                                                             compression="lz4"),
        "ros1 debian png compressed": lambda p: bagmaker.write_ros1_debian(p, frames, cmp, "compressed",
                                                                           compression="none"),
    }
    for i, (name, make) in enumerate(cases.items()):
        bag = one_file(make(tmp_path / f"bag{i}" if name.startswith("mcap") else tmp_path / f"bag{i}.bag"))
        got = upload(server, key, f"desk-{i}", bag.read_bytes())
        same_loops(got, want["grey" if "mono" in name else "rgb"])
        print(f"{name}: {len(got['loops'])} loops, equal to the folder job's")
    # A split rosbag2 bag (three files listed in metadata.yaml), through `loopd ingest`.
    split = bagmaker.write_split_mcap(tmp_path / "split", frames, img, "raw", parts=3, encoding="rgb8")
    session(server, key, "desk-split")
    same_loops(ingest(server, split, "--session", "desk-split"), want["rgb"])


def test_topics_thinning_and_robots(server, key, tmp_path):
    frames = [(p, T0 + 0.5 * i) for i, p in enumerate(CORRIDOR_REF[:20])]
    a, b = "/robot1/cam/image_raw/compressed", "/robot2/cam/image_raw/compressed"
    msgs = sorted(bagmaker.messages(frames, a, "compressed") + bagmaker.messages(frames, b, "compressed",
                                                                                 decoys=False),
                  key=lambda m: m[2])
    body = one_file(bagmaker._write_rosbag2(tmp_path / "two", msgs, "zstd", None)).read_bytes()

    def job(name, **query):
        return upload(server, key, name, body, **query)

    def robots(name):
        return sorted(call(server, key, "GET", f"/v1/sessions/{name}")[1]["robots"])

    both = job("two-both", topic=f"{a},{b}")
    assert (both["total"], robots("two-both")) == (40, ["robot1", "robot2"]), both
    assert job("two-every", topic=a, every=3)["total"] == 7  # messages 0, 3, ..., 18
    assert job("two-dt", topic=a, min_dt=1.0)["total"] == 10  # stamps every 0.5 s
    assert job("two-named", topic=b, robot_id="truck")["total"] == 20 and robots("two-named") == ["truck"]
    # The CLI lists the topics (decoys included, image topics marked) when no session is given.
    listing = subprocess.run([str(BIN), "ingest", tmp_path / "two"], capture_output=True, text=True)
    assert listing.returncode == 0, listing.stderr
    rows = {line.split()[0]: line.split() for line in listing.stdout.splitlines()[1:]}
    assert rows[a][1:] == ["sensor_msgs/msg/CompressedImage", "20", "image"], listing.stdout
    assert rows["/imu"][1:] == ["sensor_msgs/msg/Imu", "60", "-"], listing.stdout


def test_broken_bags_are_400s_that_say_what_is_wrong(server, key, tmp_path):
    frames = [(p, T0 + i) for i, p in enumerate(CORRIDOR_REF[:12])]
    img = "/robot1/cam/image_raw"
    lz4 = one_file(bagmaker.write_mcap(tmp_path / "lz4", frames, img, "raw", "mono8", compression="lz4",
                                       chunk_size=16 << 10))
    ros1 = bagmaker.write_ros1_debian(tmp_path / "d.bag", frames, img, "raw", "bgr8", compression="lz4")
    two = sorted(bagmaker.messages(frames, img, "raw", "mono8") + bagmaker.messages(frames, "/robot2/cam/image_raw",
                                                                                   "raw", "mono8", decoys=False),
                 key=lambda m: m[2])
    cases = {
        "truncated MCAP": (bagmaker.truncate(lz4, tmp_path / "t.mcap", 0.6), {}, "truncated"),
        "corrupt MCAP": (bagmaker.corrupt(lz4, tmp_path / "c.mcap", seed=1), {}, "MCAP"),
        "truncated ROS 1": (bagmaker.truncate(ros1, tmp_path / "t.bag", 0.6), {}, "truncated"),
        "corrupt ROS 1": (bagmaker.corrupt(ros1, tmp_path / "c.bag", seed=1), {}, "ROS 1 bag"),
        "MCAP without images": (one_file(bagmaker.write_imageless(tmp_path / "n", frames, img)), {},
                                "no sensor_msgs/Image or CompressedImage topic"),
        "ROS 1 without images": (bagmaker.write_imageless(tmp_path / "n.bag", frames, img, "ros1"), {},
                                 "no sensor_msgs/Image or CompressedImage topic"),
        "unknown topic": (lz4, {"topic": "/robot9/cam"}, "no topic /robot9/cam"),
        "not an image topic": (lz4, {"topic": "/imu"}, "not an image topic"),
        "two image topics, none named": (one_file(bagmaker._write_rosbag2(tmp_path / "two", two, "zstd", None)), {},
                                         "several image topics"),
        "every 0": (lz4, {"every": 0}, "every"),
        "a pose topic that is not a pose": (lz4, {"pose_topic": "/imu"}, "not a pose"),
        "a depth topic that is not an image": (lz4, {"depth_topic": "/robot1/status"}, "not a depth image"),
        "a right topic that is not an image": (lz4, {"right_topic": "/robot1/status"}, "not a right image"),
        "a right topic and a depth topic": (lz4, {"right_topic": img, "depth_topic": img}, "not both"),
        "tf without a /tf topic": (lz4, {"odom_frame": "odom", "camera_frame": "cam"}, "no topic /tf"),
        "an odom frame without a camera frame": (lz4, {"odom_frame": "odom"}, "go together"),
        "garbage": (None, {}, "tar"),
    }
    session(server, key, "broken")
    for name, (path, query, says) in cases.items():
        body = path.read_bytes() if path else b"\x89MCAQ" + bytes(range(200))
        status, answer = call(server, key, "POST", "/v1/sessions/broken/sequences", body,
                              {k: str(v) for k, v in query.items()}, "application/octet-stream")
        assert status == 400 and says in answer["error"], (name, status, answer)
        print(f"{name}: 400 {answer['error']}")
    # Nothing was stored, and the server goes on.
    assert call(server, key, "GET", "/v1/sessions/broken")[1]["frames"] == 0
    assert upload(server, key, "after-broken", lz4.read_bytes())["done"] == 12


def rgbd_bag(folder, poses):
    """A bag made here from rgbd-slambook2/tum-desk: colour (CompressedImage), depth (16UC1 Image,
    stamped 10 ms after the colour) and the camera's drifted poses (each step 10% long), as
    nav_msgs/Odometry on /odom (poses="odom") or as /tf odom -> base_link with a fixed
    base_link -> cam on /tf_static (poses="tf"), 0.4 s before and after each image (interpolated
    to it) and none near the last image. Its folder and the drifted camera poses."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    ts = bagmaker.TS2
    desk = DATA / "rgbd-slambook2/tum-desk"
    true = []
    for line in (desk / "pose.txt").read_text().split("\n")[:5]:
        x, y, z, qx, qy, qz, qw = map(float, line.split())
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rotation.from_quat([qx, qy, qz, qw]).as_matrix(), [x, y, z]
        true.append(T)
    drift = [true[0]]
    for a, b in zip(true, true[1:]):
        inc = np.linalg.inv(a) @ b
        inc[:3, 3] *= 1.1
        drift.append(drift[-1] @ inc)
    stamps = [T0 + 3.0 * i for i in range(5)]
    msgs = []
    for i, t in enumerate(stamps):
        ns = round(t * 1e9)
        msgs.append(("/cam/image_raw/compressed", "sensor_msgs/msg/CompressedImage", ns,
                     {"header": {"stamp": ns, "frame_id": "cam"}, "format": "png",
                      "data": (desk / f"color/{i + 1}.png").read_bytes()}))
        h, w, step, data = bagmaker.raw_pixels(desk / f"depth/{i + 1}.pgm", "mono16")
        dns = ns + 10_000_000
        msgs.append(("/cam/depth", "sensor_msgs/msg/Image", dns, {"header": {"stamp": dns, "frame_id": "cam"},
                     "height": h, "width": w, "encoding": "16UC1", "is_bigendian": 0, "step": step, "data": data}))

    def pose_fields(T):
        qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
        return {"x": T[0, 3], "y": T[1, 3], "z": T[2, 3]}, {"x": qx, "y": qy, "z": qz, "w": qw}

    # base_link -> cam: the camera 10 cm ahead, 20 cm up, looking along base_link's x.
    base_cam = np.eye(4)
    base_cam[:3, :3] = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix()
    base_cam[:3, 3] = [0.1, 0.0, 0.2]

    def tf(ns, parent, child, T):
        t, q = pose_fields(T)
        stamped = bagmaker.build(ts, "geometry_msgs/msg/TransformStamped", {
            "header": {"stamp": ns, "frame_id": parent}, "child_frame_id": child,
            "transform": {"translation": t, "rotation": q}})
        return ts.types["tf2_msgs/msg/TFMessage"](transforms=[stamped])

    if poses == "tf":
        msgs.append(("/tf_static", "tf2_msgs/msg/TFMessage", round(T0 * 1e9) - 1, tf(0, "base_link", "cam", base_cam)))
    for i in range(4):
        for dt in (-0.4, 0.4):
            ns = round((stamps[i] + dt) * 1e9)
            if poses == "odom":
                t, q = pose_fields(drift[i])
                msgs.append(("/odom", "nav_msgs/msg/Odometry", ns, {
                    "header": {"stamp": ns, "frame_id": "odom"}, "child_frame_id": "cam",
                    "pose": {"pose": {"position": t, "orientation": q}}}))
            else:
                msgs.append(("/tf", "tf2_msgs/msg/TFMessage", ns,
                             tf(ns, "odom", "base_link", drift[i] @ np.linalg.inv(base_cam))))
    folder = pathlib.Path(folder)
    with bagmaker.Ros2Writer(folder, version=9, storage_plugin=bagmaker.StoragePlugin.MCAP) as bag:
        conns = {}
        for topic, msgtype, t, fields in sorted(msgs, key=lambda m: m[2]):
            if topic not in conns:
                conns[topic] = bag.add_connection(topic, msgtype, typestore=ts)
            msg = bagmaker.build(ts, msgtype, fields) if isinstance(fields, dict) else fields
            bag.write(conns[topic], t, ts.serialize_cdr(msg, msgtype))
    return folder, drift


@pytest.mark.parametrize("poses", ["odom", "tf"])
def test_an_rgbd_bag_with_odometry_comes_out_as_a_loop_graph(server, key, tmp_path, poses):
    """rgbd_bag through `loopd ingest --depth-topic --camera` and --pose-topic or --odom-frame
    --camera-frame: the export's graph.g2o has a vertex for each frame the poses cover (at the
    drifted camera pose) and metric loop edges without any verdict; the frame they do not cover
    is stored without a pose and the export says its loops were left out for it."""
    bag, drift = rgbd_bag(tmp_path / "rgbd", poses)
    source = ["--pose-topic", "/odom"] if poses == "odom" else ["--odom-frame", "odom", "--camera-frame", "cam"]
    name = f"rgbd-{poses}"
    job = ingest(server, bag, "--session", name, "--topic", "/cam/image_raw/compressed", *source,
                 "--depth-topic", "/cam/depth", "--camera", "518,519,325.5,253.5",
                 "--exclude-last-frames", "0", "--min-confidence", "0", "--sequence", "false")
    assert (job["state"], job["total"], job["errors"]) == ("done", 5, []), job
    status, frames = call(server, key, "GET", f"/v1/sessions/{name}/frames", query={"limit": 10})
    assert status == 200, frames
    posed = [f for f in frames["frames"] if f.get("pose")]
    assert len(posed) == 4, frames
    for f, T in zip(posed, drift):
        got = [f["pose"][k] for k in "xyz"]
        assert max(abs(a - b) for a, b in zip(got, T[:3, 3])) < 1e-6, (f, T)

    out = subprocess.run([str(BIN), "export", name, "--out", tmp_path / "rgbd.tar", "--server",
                          f"https://127.0.0.1:{server.http_port}", "--ca", str(server.ca),
                          "--key-file", str(server.root / "bags.key")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    with tarfile.open(tmp_path / "rgbd.tar") as t:
        g2o = t.extractfile("graph.g2o").read().decode().splitlines()
        readme = t.extractfile("README.txt").read().decode()
    assert sum(l.startswith("VERTEX_SE3:QUAT") for l in g2o) == 4
    loop_edges = [l for l in g2o if l.startswith("EDGE_SE3:QUAT")][3:]  # after 3 odometry edges
    assert len(loop_edges) >= 2, (g2o, readme)
    assert "1 without a pose at an end" in readme, readme
    assert "graph.g2o:" in out.stderr and "loop edges" in out.stderr, out.stderr


def test_a_stereo_bag_gives_metric_loops(server, key, tmp_path):
    """EuRoC's four stereo pairs as a bag made here (left and right CompressedImage; the right
    stamped 1 ms after its left) into sessions created with the calibrated stereo camera through
    the client: with `loopd ingest --right-topic` the loops (1, 0) and (3, 2) get metric poses near
    the ground truth's 0.43 m and 0.32 m; the same bag without it gives none."""
    from conftest import euroc_stereo

    camera, stereo = euroc_stereo()
    ts = bagmaker.TS2
    msgs = []
    for i in range(4):
        for side, topic, dt in (("left", "/cam0/image_raw/compressed", 0), ("right", "/cam1/image_raw/compressed", 1)):
            ns = round((T0 + 3.0 * i) * 1e9) + dt * 1_000_000
            msgs.append((topic, ns, {"header": {"stamp": ns, "frame_id": side}, "format": "png",
                                     "data": (DATA / f"euroc-lcd/{side}_img_{i}.png").read_bytes()}))
    folder = tmp_path / "stereo"
    with bagmaker.Ros2Writer(folder, version=9, storage_plugin=bagmaker.StoragePlugin.MCAP) as bag:
        conns = {}
        for topic, ns, fields in sorted(msgs, key=lambda m: m[1]):
            msgtype = "sensor_msgs/msg/CompressedImage"
            if topic not in conns:
                conns[topic] = bag.add_connection(topic, msgtype, typestore=ts)
            bag.write(conns[topic], ns, ts.serialize_cdr(bagmaker.build(ts, msgtype, fields), msgtype))

    with Client(server.grpc, ca=server.ca, key=key) as c:
        for name, right in (("stereo-bag", ["--right-topic", "/cam1/image_raw/compressed"]), ("mono-bag", [])):
            c.create_session(name, camera=camera, stereo=stereo)
            job = ingest(server, folder, "--session", name, "--topic", "/cam0/image_raw/compressed", *right,
                         "--exclude-last-frames", "0", "--min-confidence", "0", "--sequence", "false")
            assert (job["state"], job["total"], job["errors"]) == ("done", 4, []), job
            for q, m, distance in ((1, 0, 0.432), (3, 2, 0.317)):
                best = c.query(name, "cam0", frame_id=q, options=query_options(
                    k=1, scope="all", frame_id_from=m, frame_id_to=m, exclude_last_frames=0))[0]
                v = best.verification
                assert best.frame_id == m and v.verified, (name, q, v)
                if not right:
                    assert not v.metric, (name, q, v)
                    continue
                assert v.metric and len(v.covariance) == 36, (name, q, v)
                p = v.relative_pose
                norm = (p.tx ** 2 + p.ty ** 2 + p.tz ** 2) ** 0.5
                assert abs(norm - distance) < 0.1, (q, m, norm)
