"""The ROS 2 bridge (`loopd ros2`) against a real ROS 2 peer.

rclpy from PyPI's ROS 2 Kilted wheels plays the fleet's robots; a real `loopd serve` and the
bridge run beside it, all in a network namespace of their own (scripts/ros2-test: DDS multicast
never leaves it). loopd_msgs/LoopClosure is the message built from ros/loopd_msgs by
scripts/ros2-env, so rclpy decodes what the bridge publishes with the shipped definition, and
rosbags decodes the same CDR bytes from the .msg text alone.

What the robots publish is real data: the Corridor frames (two robots, CompressedImage), the
slambook2 desk frames (raw rgb8, with a CameraInfo) and the TUM desk sweep with its poses as
odometry. Each answer is compared, pair for pair, with what the gRPC path (the Python client,
AddAndQuery) answers for the same frames in a session of its own.
"""
import math
import os
import pathlib
import re
import signal
import socket
import subprocess
import threading
import time
import urllib.error
import urllib.request
import json

import numpy as np
import pytest
import rclpy
from PIL import Image as PILImage
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.serialization import serialize_message

from loopd_client import Client, Frame, pb
from loopd_msgs.msg import LoopClosure
from nav_msgs.msg import Odometry
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from visualization_msgs.msg import MarkerArray

ROOT = pathlib.Path(__file__).resolve().parents[2]
DATA = pathlib.Path(os.environ.get("LOOPD_SHARED_DATA", ROOT.parent / "shared" / "data"))
LOOPD = str(ROOT / "target" / "release" / "loopd")
MSG = ROOT / "ros" / "loopd_msgs" / "msg" / "LoopClosure.msg"
# TUM fr1 (the slambook2 desk frames) and the TUM desk sweep (rgbd-slambook2/tum-desk/README).
DESK_CAMERA = (517.3, 516.5, 318.6, 255.3)

# Every wait is bounded: a bridge that stops answering fails the test instead of hanging it.
SENT_TIMEOUT = 180.0


def free_ports(n):
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def wait_until(what, check, timeout):
    deadline = time.time() + timeout
    while time.time() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


class Server:
    """A real `loopd serve` on loopback, on a data directory that outlives kill -9."""

    def __init__(self, tmp):
        self.data = tmp / "data"
        self.log = open(tmp / "server.log", "ab")
        self.http, self.grpc = free_ports(2)
        self.proc = None
        self.start()

    def start(self):
        self.proc = subprocess.Popen(
            [LOOPD, "serve", "--device", "cpu", "--data-dir", str(self.data),
             "--http-addr", f"127.0.0.1:{self.http}", "--grpc-addr", f"127.0.0.1:{self.grpc}"],
            cwd=ROOT, stdout=self.log, stderr=subprocess.STDOUT)

        def ready():
            assert self.proc.poll() is None, "the server exited (server.log)"
            try:
                return urllib.request.urlopen(f"http://127.0.0.1:{self.http}/readyz", timeout=1).status == 200
            except (urllib.error.URLError, OSError):
                return False

        wait_until("the server to be ready", ready, 240)

    def kill9(self):
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()

    def get(self, path):
        with urllib.request.urlopen(f"http://127.0.0.1:{self.http}{path}", timeout=10) as r:
            return json.loads(r.read())

    def frames(self, session):
        out, after = [], None
        while True:
            page = self.get(f"/v1/sessions/{session}/frames?limit=1000" + (f"&after={after}" if after is not None else ""))
            out += page["frames"]
            after = page.get("next")
            if after is None:
                return out


class Bridge:
    """`loopd ros2`, its counters read from its /metrics."""

    def __init__(self, tmp, name, server, *args):
        (self.port,) = free_ports(1)
        self.log_path = tmp / f"{name}.log"
        self.proc = subprocess.Popen(
            [LOOPD, "ros2", "--server", f"127.0.0.1:{server.grpc}", "--metrics-addr", f"127.0.0.1:{self.port}",
             "--node-name", name, *args],
            cwd=ROOT, stdout=open(self.log_path, "ab"), stderr=subprocess.STDOUT)

    def metrics(self):
        assert self.proc.poll() is None, f"the bridge exited: {self.log_path.read_text()[-3000:]}"
        try:
            text = urllib.request.urlopen(f"http://127.0.0.1:{self.port}/metrics", timeout=2).read().decode()
        except (urllib.error.URLError, OSError):
            return {}
        values = {}
        for line in text.splitlines():
            m = re.match(r'^(\w+)\{(.*)\} (\S+)$', line)
            if m:
                labels = tuple(sorted(re.findall(r'(\w+)="([^"]*)"', m.group(2))))
                values[(m.group(1), labels)] = float(m.group(3))
        return values

    def count(self, name, **labels):
        return self.metrics().get((name, tuple(sorted(labels.items()))), 0.0)

    def stop(self):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()


class Robots(Node):
    """The fleet's side: camera publishers, and the bridge's loop closures as received."""

    def __init__(self, name, loops_topic, markers_topic):
        super().__init__(name)
        kept = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.loops, self.raw, self.markers = [], [], []
        self.create_subscription(LoopClosure, loops_topic, self.loops.append, kept)
        # The same messages as CDR bytes, for rosbags.
        self.create_subscription(LoopClosure, loops_topic, self.raw.append, kept, raw=True)
        self.create_subscription(MarkerArray, markers_topic, self.markers.append, kept)
        self.publishers_ = {}

    def publisher(self, kind, topic):
        if topic not in self.publishers_:
            qos = QoSProfile(depth=10) if kind is Odometry or kind is CameraInfo else qos_profile_sensor_data
            p = self.create_publisher(kind, topic, qos)
            # Published only once the bridge has found and subscribed the topic.
            wait_until(f"the bridge to subscribe {topic}", lambda: p.get_subscription_count() > 0, 30)
            self.publishers_[topic] = p
        return self.publishers_[topic]


@pytest.fixture(scope="module")
def ros():
    rclpy.init()
    executor = SingleThreadedExecutor()
    thread = threading.Thread(target=executor.spin, daemon=True)
    nodes = []

    def make(name, loops_topic, markers_topic):
        n = Robots(name, loops_topic, markers_topic)
        executor.add_node(n)
        nodes.append(n)
        return n

    thread.start()
    yield make
    executor.shutdown()
    for n in nodes:
        n.destroy_node()
    rclpy.shutdown()


@pytest.fixture
def server(tmp_path):
    s = Server(tmp_path)
    yield s
    s.stop()


def stamp(t):
    from builtin_interfaces.msg import Time
    sec = math.floor(t)
    return Time(sec=int(sec), nanosec=int(round((t - sec) * 1e9)))


def compressed(topic_frame, t, jpeg):
    m = CompressedImage()
    m.header.stamp, m.header.frame_id, m.format, m.data = stamp(t), topic_frame, "jpeg", jpeg
    return m


def raw_rgb8(t, png_path, *, encoding="rgb8", step_less=0, cut=0):
    pixels = np.asarray(PILImage.open(png_path).convert("RGB"))
    h, w, _ = pixels.shape
    m = Image()
    m.header.stamp, m.header.frame_id = stamp(t), "desk_camera"
    m.height, m.width, m.encoding, m.is_bigendian, m.step = h, w, encoding, 0, w * 3 - step_less
    data = pixels.tobytes()
    m.data = data[:len(data) - cut] if cut else data
    return m


def send(bridge, robot, publish, expected_received, expected_sent, counter="loopd_ros2_keyframes_total"):
    """Publishes a keyframe's messages and waits until the bridge has taken it (`counter`), then
    until it is stored. Camera topics are best effort: a message lost on the way (none seen on
    loopback, but it may be) is published again with the same stamp, which the bridge takes as the
    same keyframe."""
    for _ in range(5):
        publish()
        try:
            wait_until("the bridge to take it", lambda: bridge.count(counter, robot=robot) >= expected_received, 10)
            break
        except AssertionError:
            continue
    else:
        raise AssertionError(f"{robot}: the bridge never received message {expected_received}")
    if expected_sent is not None:
        wait_until(f"{robot}'s keyframe {expected_sent} to be stored",
                   lambda: bridge.count("loopd_ros2_frames_sent_total", robot=robot) >= expected_sent, SENT_TIMEOUT)


def as_tuple(l):
    """A LoopClosure (rclpy) as what the gRPC path answers for it."""
    pose = None
    if l.has_pose:
        p, q = l.pose.position, l.pose.orientation
        pose = (q.x, q.y, q.z, q.w, p.x, p.y, p.z)
    return (l.key_from, l.rank, l.key_to, l.robot_from_id, l.robot_to_id, round(l.score, 5), l.checked, l.verified,
            l.inliers, l.matches, pose)


def expected(frame_id, robot, match, rank):
    v = match.verification if match.HasField("verification") else None
    pose = None
    if v is not None and v.HasField("relative_pose"):
        r = v.relative_pose
        pose = (r.qx, r.qy, r.qz, r.qw, r.tx, r.ty, r.tz)
    return (frame_id, rank, match.frame_id, robot, match.robot_id, round(match.score, 5), v is not None,
            bool(v and v.verified), v.inliers if v else 0, v.matches if v else 0, pose)


def same_poses(a, b):
    if a is None or b is None:
        return a is b
    return all(abs(x - y) < 1e-6 for x, y in zip(a, b))


def compare(got, want):
    got, want = sorted(got, key=lambda t: (t[0], t[1])), sorted(want, key=lambda t: (t[0], t[1]))
    assert [g[:-1] for g in got] == [w[:-1] for w in want]
    for g, w in zip(got, want):
        assert same_poses(g[-1], w[-1]), (g, w)


def check_cdr(node):
    """The bytes on the topic decode with rosbags against the shipped .msg text, to the same values
    rclpy decoded with the type built from it."""
    store = get_typestore(Stores.LATEST)
    store.register(get_types_from_msg(MSG.read_text(), "loopd_msgs/msg/LoopClosure"))
    assert len(node.raw) == len(node.loops) > 0
    for raw, l in zip(node.raw, node.loops):
        # Not byte for byte: CDR leaves the content of alignment padding to the writer.
        assert len(raw) == len(serialize_message(l))
        m = store.deserialize_cdr(raw, "loopd_msgs/msg/LoopClosure")
        assert (m.key_from, m.key_to, m.robot_from, m.robot_to, m.type) == (l.key_from, l.key_to, l.robot_from,
                                                                           l.robot_to, l.type)
        assert (m.robot_from_id, m.robot_to_id, m.session_id, m.inliers, m.verified, m.rank) == (
            l.robot_from_id, l.robot_to_id, l.session_id, l.inliers, l.verified, l.rank)
        assert m.header.stamp.sec == l.header.stamp.sec and m.stamp_to.nanosec == l.stamp_to.nanosec
        assert list(m.covariance) == list(l.covariance) and len(m.covariance) == 36
        assert m.pose.orientation.w == l.pose.orientation.w and m.score == pytest.approx(l.score)


def stored_once(server, session, sent):
    """Every keyframe stored exactly once: the session's frames are the (robot, stamp) sent."""
    frames = server.frames(session)
    seen = [(f["robot_id"], round(f["timestamp"], 6)) for f in frames]
    assert len(seen) == len(set(seen)), "a keyframe stored twice"
    assert sorted(seen) == sorted((r, round(t, 6)) for r, t in sent)


def test_two_robots_get_the_loops_the_grpc_path_answers_and_a_server_kill_loses_no_keyframe(tmp_path, server, ros):
    bridge = Bridge(tmp_path, "loopd_corridor", server, "--session", "corridor",
                    "--images", "/*/camera/image_raw/compressed", "--publish", "all")
    node = ros("corridor_fleet", "/loopd/loop_closures", "/loopd/loop_markers")
    try:
        corridor = DATA / "corridor"
        # r1 maps the corridor (ref), r2 drives it again (query): every 5th frame.
        plan = [("r1", 1000.0 + i, corridor / "ref" / f"{i:07d}.jpg") for i in range(0, 111, 5)]
        plan += [("r2", 5000.0 + i, corridor / "query" / f"{i:07d}.jpg") for i in range(0, 111, 5)]
        assert all(p.exists() for _, _, p in plan), f"Corridor frames missing under {corridor}"
        counts = {"r1": 0, "r2": 0}
        kill_at = len(plan) - 8  # r2, mid-stream
        down = []
        for n, (robot, t, path) in enumerate(plan):
            pub = node.publisher(CompressedImage, f"/{robot}/camera/image_raw/compressed")
            counts[robot] += 1
            msg = compressed(f"{robot}_camera", t, path.read_bytes())
            if n == kill_at:
                # kill -9 right after the bridge took the frame: its send is in flight or about to be.
                send(bridge, robot, lambda: pub.publish(msg), counts[robot], None)
                server.kill9()
                down = [n]
                continue
            if down and len(down) < 4:
                # The server is down: the bridge queues them (its queue holds 16) and retries.
                send(bridge, robot, lambda: pub.publish(msg), counts[robot], None)
                down.append(n)
                if len(down) == 4:
                    assert bridge.count("loopd_ros2_frames_sent_total", robot="r2") < counts["r2"]
                    server.start()
                continue
            send(bridge, robot, lambda: pub.publish(msg), counts[robot], counts[robot])
        assert bridge.count("loopd_ros2_send_retries_total", robot="r2") > 0, "the kill was never seen"
        assert bridge.count("loopd_ros2_frames_dropped_total", robot="r2") == 0
        stored_once(server, "corridor", [(r, t) for r, t, _ in plan])

        # The gRPC path: the same frames, in the same order, in a session of its own.
        want = []
        with Client(f"127.0.0.1:{server.grpc}") as c:
            c.create_session("corridor-grpc")
            for robot, t, path in plan:
                a = c.add_and_query("corridor-grpc", robot, Frame(image=path.read_bytes(), timestamp=t))
                want += [expected(a.frame_id, robot, m, i) for i, m in enumerate(a.matches)]
        assert want, "the gRPC path answered no candidate at all"
        wait_until("every loop closure to arrive", lambda: len(node.loops) >= len(want), 60)
        time.sleep(1.0)
        compare([as_tuple(l) for l in node.loops], want)
        assert bridge.count("loopd_ros2_loops_published_total", robot="r2") + bridge.count(
            "loopd_ros2_loops_published_total", robot="r1") == len(want)
        # Robot indices: the order the bridge met them.
        assert {(l.robot_from_id, l.robot_from) for l in node.loops} <= {("r1", 0), ("r2", 1)}
        assert all(l.type in (LoopClosure.LOOPCLOSE, LoopClosure.REJECTED_LOOPCLOSE) for l in node.loops)
        assert any(l.robot_from_id == "r2" and l.robot_to_id == "r1" for l in node.loops)
        check_cdr(node)
    finally:
        bridge.stop()


def test_a_desk_loop_with_camera_info_odometry_markers_and_bad_input(tmp_path, server, ros):
    bridge = Bridge(tmp_path, "loopd_desk", server, "--session", "desk",
                    "--images", "/desk/camera/image_raw", "--images", "/sweep/camera/image_raw",
                    "--camera-info", "/desk/camera/camera_info", "--camera-wait", "120", "--odom", "/*/odom",
                    "--loops-topic", "/desk/loop_closures", "--markers-topic", "/desk/loop_markers")
    node = ros("desk_fleet", "/desk/loop_closures", "/desk/loop_markers")
    try:
        # A driver that is not calibrated yet publishes zeros: refused, counted, logged.
        info = node.publisher(CameraInfo, "/desk/camera/camera_info")
        zeros = CameraInfo()
        zeros.width, zeros.height = 640, 480
        info.publish(zeros)
        wait_until("the zero CameraInfo to be refused",
                   lambda: bridge.count("loopd_ros2_rejected_total", robot="desk", what="camera_info") >= 1, 30)
        fx, fy, cx, cy = DESK_CAMERA
        good = CameraInfo()
        good.width, good.height, good.distortion_model = 640, 480, "plumb_bob"
        good.d = [0.0] * 5
        good.k = [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]

        def session_made():
            info.publish(good)
            try:
                return server.get("/v1/sessions/desk")["id"] == "desk"
            except urllib.error.HTTPError:
                return False

        wait_until("the session to be made with the CameraInfo", session_made, 60)

        desk = DATA / "slambook2-ch11"
        sweep = DATA / "rgbd-slambook2" / "tum-desk"
        poses = [list(map(float, line.split())) for line in (sweep / "pose.txt").read_text().split("\n") if line.strip()]
        plan = [("desk", 100.0 + i, desk / f"{i}.png", None) for i in range(1, 11)]
        plan += [("sweep", 200.0 + i, sweep / "color" / f"{i}.png", poses[i - 1]) for i in range(1, 6)]
        cam = node.publisher(Image, "/desk/camera/image_raw")
        received = {"desk": 0, "sweep": 0}
        sent = {"desk": 0, "sweep": 0}
        for robot, t, path, pose in plan:
            pub = node.publisher(Image, f"/{robot}/camera/image_raw")
            msg = raw_rgb8(t, path)
            received[robot] += 1
            sent[robot] += 1
            if pose is None:
                send(bridge, robot, lambda: pub.publish(msg), received[robot], sent[robot])
            else:
                odom = node.publisher(Odometry, f"/{robot}/odom")
                o = Odometry()
                o.header.stamp, o.header.frame_id, o.child_frame_id = stamp(t), "map", f"{robot}_camera"
                x, y, z, qx, qy, qz, qw = pose
                o.pose.pose.position.x, o.pose.pose.position.y, o.pose.pose.position.z = x, y, z
                o.pose.pose.orientation.x, o.pose.pose.orientation.y = qx, qy
                o.pose.pose.orientation.z, o.pose.pose.orientation.w = qz, qw

                def both(o=o, msg=msg, pub=pub, odom=odom):
                    odom.publish(o)
                    time.sleep(0.2)
                    pub.publish(msg)

                send(bridge, robot, both, received[robot], sent[robot])
            if robot == "desk" and t == 103.0:
                # Bad frames from the robot: each refused and counted; the bridge goes on.
                for n, bad in enumerate([raw_rgb8(103.2, path, encoding="bayer_rggb8"),
                                         raw_rgb8(103.4, path, cut=1000),
                                         raw_rgb8(103.6, path, step_less=1)], start=1):
                    rejected = lambda: bridge.count("loopd_ros2_rejected_total", robot="desk", what="image")
                    for _ in range(5):
                        cam.publish(bad)
                        try:
                            wait_until(f"bad frame {n} to be refused", lambda: rejected() >= n, 10)
                            break
                        except AssertionError:
                            continue
        assert bridge.proc.poll() is None
        assert bridge.count("loopd_ros2_rejected_total", robot="desk", what="image") == 3
        assert bridge.count("loopd_ros2_frames_sent_total", robot="desk") == 10
        stored_once(server, "desk", [(r, t) for r, t, _, _ in plan])
        log = bridge.log_path.read_text()
        assert "bayer_rggb8" in log and "shorter than a row" in log and "not a calibrated camera" in log, log[-3000:]

        want, ids = [], {}
        with Client(f"127.0.0.1:{server.grpc}") as c:
            c.create_session("desk-grpc", camera=list(DESK_CAMERA))
            for robot, t, path, pose in plan:
                p = pb.Pose(x=pose[0], y=pose[1], z=pose[2], qx=pose[3], qy=pose[4], qz=pose[5], qw=pose[6]) if pose else None
                a = c.add_and_query("desk-grpc", robot, Frame(image=path.read_bytes(), timestamp=t, pose=p))
                ids[(robot, t)] = a.frame_id
                want += [expected(a.frame_id, robot, m, i) for i, m in enumerate(a.matches)
                         if m.HasField("verification") and m.verification.verified]
        wait_until("every verified loop to arrive", lambda: len(node.loops) >= len(want), 60)
        time.sleep(1.0)
        compare([as_tuple(l) for l in node.loops], want)

        # The slambook2 loop: frame 10 closes on frame 1, verified, with a relative pose.
        loop = [l for l in node.loops if (l.key_from, l.key_to) == (ids[("desk", 110.0)], ids[("desk", 101.0)])]
        assert len(loop) == 1, [as_tuple(l) for l in node.loops]
        l = loop[0]
        assert l.verified and l.type == LoopClosure.LOOPCLOSE and l.has_pose and not l.metric
        q, p = l.pose.orientation, l.pose.position
        assert abs(math.sqrt(q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2) - 1) < 1e-6
        assert abs(math.sqrt(p.x ** 2 + p.y ** 2 + p.z ** 2) - 1) < 1e-6, "a monocular pose: unit translation"
        assert l.header.stamp.sec == 110 and l.stamp_to.sec == 101 and l.session_id == "desk"

        # Loops between frames with odometry poses: a marker line from one position to the other.
        position = {ids[("sweep", t)]: tuple(pose[:3]) for r, t, _, pose in plan if r == "sweep"}
        lines = {(tuple(round(v, 9) for v in (m.points[0].x, m.points[0].y, m.points[0].z)),
                  tuple(round(v, 9) for v in (m.points[1].x, m.points[1].y, m.points[1].z)))
                 for a in node.markers for m in a.markers}
        between = [l for l in node.loops if l.key_from in position and l.key_to in position]
        assert between, "no verified loop within the sweep"
        for l in between:
            a, b = (tuple(round(v, 9) for v in position[k]) for k in (l.key_from, l.key_to))
            assert (a, b) in lines, (a, b, lines)
        assert all(a.markers[0].header.frame_id == "map" and a.markers[0].type == 5 for a in node.markers)
        check_cdr(node)
    finally:
        bridge.stop()
