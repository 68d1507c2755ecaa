"""The exported loop graph drives a real back end: KITTI 00's ground-truth poses (every 5th
frame), stored with drifted odometry; loopd finds the revisits (descriptors made from the true
place, as a perfect place recogniser would give: KITTI's images are not on these machines); the
client accepts each candidate within 5 m of the truth with the true relative pose (its own
registration) and rejects the rest; the export's graph.g2o is optimised with GTSAM and the
trajectory error measured with evo must drop more than 5x against the odometry; `evo_traj tum
--full_check` accepts every exported .tum file."""
from __future__ import annotations

import io
import json
import pathlib
import subprocess
import sys
import tarfile
import urllib.request

import numpy as np
from conftest import DATA

from loopd_client import Client, Frame, pb, query_options

import gtsam
from evo.core import metrics
from evo.core.trajectory import PoseTrajectory3D
from scipy.spatial.transform import Rotation

STEP = 5
SIGMA_PLACE = 4.0  # metres: descriptor similarity falls off with distance like exp(-d^2 / 2 sigma^2)


def kitti_poses():
    rows = np.loadtxt(DATA / "kitti-poses/00_with_timestamps.txt")[::STEP]
    poses = []
    for r in rows:
        T = np.eye(4)
        T[:3, :4] = r[1:].reshape(3, 4)
        poses.append(T)
    return rows[:, 0], poses


def drifted(true):
    """Odometry: each true increment with a yaw bias and noise and a 1% scale error, integrated."""
    rng = np.random.default_rng(7)
    out = [true[0].copy()]
    for a, b in zip(true, true[1:]):
        inc = np.linalg.inv(a) @ b
        noise = np.eye(4)
        noise[:3, :3] = Rotation.from_euler("y", 0.0008 + rng.normal(0, 0.0005)).as_matrix()
        inc = inc.copy()
        inc[:3, 3] *= 1.01 + rng.normal(0, 0.003)
        out.append(out[-1] @ inc @ noise)
    return out


def place_descriptors(true, dim):
    """Random Fourier features of the true ground-plane position (x, z)."""
    rng = np.random.default_rng(11)
    w = rng.normal(0, 1 / SIGMA_PLACE, size=(dim, 2))
    b = rng.uniform(0, 2 * np.pi, size=dim)
    xz = np.array([[T[0, 3], T[2, 3]] for T in true])
    return np.cos(xz @ w.T + b)


def pose_msg(T):
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    return pb.Pose(x=T[0, 3], y=T[1, 3], z=T[2, 3], qx=qx, qy=qy, qz=qz, qw=qw)


def relative(Ta, Tb):
    T = np.linalg.inv(Ta) @ Tb
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    return pb.RelativePose(qx=qx, qy=qy, qz=qz, qw=qw, tx=T[0, 3], ty=T[1, 3], tz=T[2, 3])


def trajectory(stamps, Ts):
    xyz = np.array([T[:3, 3] for T in Ts])
    wxyz = np.array([np.roll(Rotation.from_matrix(T[:3, :3]).as_quat(), 1) for T in Ts])
    return PoseTrajectory3D(positions_xyz=xyz, orientations_quat_wxyz=wxyz, timestamps=np.asarray(stamps))


def ate(reference, estimate):
    est = estimate
    est.align(reference, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, est))
    return ape.get_statistic(metrics.StatisticsType.rmse)


def test_exported_graph_optimised_with_gtsam_beats_odometry_5x(server, tmp_path):
    stamps, true = kitti_poses()
    odometry = drifted(true)
    key = server.tenant("kitti")
    with Client(server.grpc, key=key, ca=server.ca) as c:
        dim = c.create_session("kitti00", exist_ok=True).dim
        descriptors = place_descriptors(true, dim)
        options = query_options(k=1, verify=False, exclude_last_seconds=60.0, min_score=0.6)
        for i, (t, T) in enumerate(zip(stamps, odometry)):
            c.add_and_query("kitti00", "car", Frame(descriptor=descriptors[i].tolist(), timestamp=float(t),
                                                    frame_id=i, pose=pose_msg(T)), options)
        loops = list(c.loops("kitti00"))
        accepted = 0
        covariance = np.diag([0.05**2] * 3 + [0.01**2] * 3).ravel().tolist()
        for lp in loops:
            q, m = lp.query_frame, lp.match_frame
            if np.linalg.norm(true[q][:3, 3] - true[m][:3, 3]) < 5.0:
                c.set_verdict("kitti00", q, m, True, relative_pose=relative(true[q], true[m]), covariance=covariance)
                accepted += 1
            else:
                c.set_verdict("kitti00", q, m, False)
    assert accepted >= 30, f"{accepted} of {len(loops)} kept loops at the true place"

    request = urllib.request.Request(f"https://127.0.0.1:{server.http_port}/v1/sessions/kitti00/export",
                                     headers={"Authorization": f"Bearer {key}"})
    with urllib.request.urlopen(request, context=server.ssl) as r:
        assert r.headers["Content-Type"] == "application/x-tar"
        archive = tarfile.open(fileobj=io.BytesIO(r.read()))
    archive.extractall(tmp_path / "export", filter="data")
    out = tmp_path / "export"
    frames = (out / "frames.csv").read_text().splitlines()
    assert len(frames) == len(true) + 1
    loops_csv = (out / "loops.csv").read_text().splitlines()
    assert len(loops_csv) == len(loops) + 1 and sum(",accepted," in l for l in loops_csv) == accepted
    g2o = (out / "graph.g2o").read_text().splitlines()
    assert sum(l.startswith("VERTEX_SE3:QUAT") for l in g2o) == len(true)
    assert sum(l.startswith("EDGE_SE3:QUAT") for l in g2o) == len(true) - 1 + accepted

    for tum in sorted((out / "trajectories").glob("*.tum")):
        check = subprocess.run([str(pathlib.Path(sys.executable).parent / "evo_traj"), "tum", str(tum), "--full_check"],
                               capture_output=True, text=True)
        assert check.returncode == 0, check.stdout + check.stderr

    graph, initial = gtsam.readG2o(str(out / "graph.g2o"), True)
    prior = gtsam.noiseModel.Diagonal.Variances(np.full(6, 1e-8))
    graph.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), prior))
    result = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams()).optimize()
    optimised = [result.atPose3(i).matrix() for i in range(len(true))]

    before = ate(trajectory(stamps, true), trajectory(stamps, odometry))
    after = ate(trajectory(stamps, true), trajectory(stamps, optimised))
    print(json.dumps({"frames": len(true), "loops_kept": len(loops), "accepted": accepted,
                      "ate_odometry_m": round(before, 2), "ate_optimised_m": round(after, 2)}))
    assert after * 5 < before, f"ATE {before:.2f} m -> {after:.2f} m"
