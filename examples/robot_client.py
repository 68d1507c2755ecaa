#!/usr/bin/env python3
"""A robot streaming keyframes to loopd over gRPC and printing its loop candidates; verified loops
(ORB + RANSAC on the server) are marked, with the relative pose when the session has a camera.

The client code is generated from proto/loopd/v1/loopd.proto at start (grpcio-tools), so it
always matches the server's API.

  python examples/robot_client.py --server 127.0.0.1:50051 --session corridor --create \\
      --robot mapper ../shared/data/corridor/ref
  python examples/robot_client.py --server 127.0.0.1:50051 --session corridor \\
      --robot visitor --scope other ../shared/data/corridor/query
"""
import argparse
import os
import pathlib
import sys
import tempfile
import time

import grpc
from grpc_tools import protoc

ROOT = pathlib.Path(__file__).resolve().parent.parent
IMAGE_EXTENSIONS = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"}


def generated_modules():
    out = tempfile.mkdtemp(prefix="loopd-proto-")
    include = os.path.join(os.path.dirname(protoc.__file__), "_proto")
    rc = protoc.main(["protoc", f"-I{ROOT / 'proto'}", f"-I{include}", f"--python_out={out}",
                      f"--grpc_python_out={out}", str(ROOT / "proto/loopd/v1/loopd.proto")])
    if rc != 0:
        sys.exit(f"protoc failed ({rc})")
    sys.path.insert(0, out)
    from loopd.v1 import loopd_pb2, loopd_pb2_grpc  # noqa: E402
    return loopd_pb2, loopd_pb2_grpc


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder", help="images, streamed in file-name order")
    ap.add_argument("--server", default="127.0.0.1:50051")
    ap.add_argument("--session", required=True)
    ap.add_argument("--create", action="store_true", help="create the session first (ok if it exists)")
    ap.add_argument("--robot", required=True)
    ap.add_argument("--k", type=int, default=3)
    ap.add_argument("--scope", choices=["all", "same", "other"], default="all")
    ap.add_argument("--exclude-last", type=int, default=10, help="skip this robot's own last N frames")
    ap.add_argument("--fps", type=float, default=0, help="pace the stream (0: as fast as possible)")
    ap.add_argument("--camera", metavar="FX,FY,CX,CY[,K1,K2,P1,P2,K3]",
                    help="intrinsics for a new session (--create): verified loops then carry a relative pose")
    ap.add_argument("--no-verify", action="store_true", help="descriptor ranking only")
    ap.add_argument("--require-matches-from", metavar="ROBOT",
                    help="exit 1 unless most frames' best match is a frame of ROBOT (for CI)")
    a = ap.parse_args()

    pb, rpc = generated_modules()
    channel = grpc.insecure_channel(a.server)
    grpc.channel_ready_future(channel).result(timeout=60)
    stub = rpc.LoopdStub(channel)
    if a.create:
        try:
            camera = None
            if a.camera:
                v = [float(x) for x in a.camera.split(",")]
                camera = pb.Camera(fx=v[0], fy=v[1], cx=v[2], cy=v[3], distortion=v[4:])
            stub.CreateSession(pb.CreateSessionRequest(id=a.session, name=a.session, camera=camera))
        except grpc.RpcError as e:
            if e.code() != grpc.StatusCode.ALREADY_EXISTS:
                raise
    scope = {"all": pb.SCOPE_ALL, "same": pb.SCOPE_SAME_ROBOT, "other": pb.SCOPE_OTHER_ROBOTS}[a.scope]
    files = sorted(p for p in pathlib.Path(a.folder).iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        sys.exit(f"no images in {a.folder}")

    def frames():
        t0 = time.time()
        for i, path in enumerate(files):
            if a.fps > 0:
                time.sleep(max(0.0, t0 + i / a.fps - time.time()))
            yield pb.AddFrameRequest(
                session_id=a.session, robot_id=a.robot, timestamp=time.time(), image=path.read_bytes(),
                metadata_json='{"file": "%s"}' % path.name,
                options=pb.QueryOptions(k=a.k, scope=scope, exclude_last_frames=a.exclude_last,
                                        verify=not a.no_verify))

    def describe(m):
        text = f"{m.robot_id}/{m.frame_id} ({m.score:.3f})"
        if not m.HasField("verification"):
            return text
        v = m.verification
        if not v.verified:
            return text + " unverified"
        text += f" VERIFIED {v.inliers} inliers"
        if v.HasField("relative_pose"):
            p = v.relative_pose
            text += (f" q=({p.qx:.3f},{p.qy:.3f},{p.qz:.3f},{p.qw:.3f})"
                     f" t=({p.tx:.2f},{p.ty:.2f},{p.tz:.2f})")
        return text

    from_robot = failed = verified = 0
    for path, answer in zip(files, stub.StreamFrames(frames())):
        if answer.error:
            failed += 1
            print(f"{path.name}: error {answer.error_code}: {answer.error}")
            continue
        if not answer.matches:
            print(f"{path.name}: frame {answer.frame_id}, no loop candidates")
            continue
        best = answer.matches[0]
        from_robot += best.robot_id == a.require_matches_from
        verified += best.verification.verified
        cands = ", ".join(describe(m) for m in answer.matches)
        print(f"{path.name}: frame {answer.frame_id}, candidates {cands}")
    print(f"{len(files)} frames streamed, {failed} failed, {verified} verified loops")
    if failed:
        sys.exit(1)
    if a.require_matches_from and from_robot * 2 < len(files):
        sys.exit(f"only {from_robot}/{len(files)} best matches were frames of {a.require_matches_from}")


if __name__ == "__main__":
    main()
