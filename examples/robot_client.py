#!/usr/bin/env python3
"""A robot streaming keyframes to loopd over gRPC and printing its loop candidates; verified loops
(ORB + RANSAC on the server) are marked, with the relative pose when the session has a camera.

It uses the client package (pip install clients/python): TLS and a key, retries with backoff, and
a stream that resumes after a server restart from the last acknowledged frame (with
--frame-id-base, exactly once).

  python examples/robot_client.py --server 127.0.0.1:50051 --session corridor --create \\
      --robot mapper ../shared/data/corridor/ref
  python examples/robot_client.py --server loopd.example:50051 --ca ca.pem --key-file robot.key \\
      --session corridor --robot visitor --scope other ../shared/data/corridor/query
"""
import argparse
import json
import os
import pathlib
import sys
import time

from loopd_client import Client, Frame, RetryPolicy, query_options

IMAGE_EXTENSIONS = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"}


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
        text += f" q=({p.qx:.3f},{p.qy:.3f},{p.qz:.3f},{p.qw:.3f}) t=({p.tx:.2f},{p.ty:.2f},{p.tz:.2f})"
    return text


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder", help="images, streamed in file-name order")
    ap.add_argument("--server", default=os.environ.get("LOOPD_SERVER", "127.0.0.1:50051"))
    ap.add_argument("--ca", help="the server's CA certificate (PEM): TLS on")
    ap.add_argument("--key-file", help="a file holding this robot's tenant key (or set LOOPD_KEY)")
    ap.add_argument("--session", required=True)
    ap.add_argument("--create", action="store_true", help="create the session first (ok if it exists)")
    ap.add_argument("--robot", required=True)
    ap.add_argument("--k", type=int, default=3)
    ap.add_argument("--scope", choices=["all", "same", "other"], default="all")
    ap.add_argument("--exclude-last", type=int, default=10, help="skip this robot's own last N frames")
    ap.add_argument("--fps", type=float, default=0, help="pace the stream (0: as fast as possible)")
    ap.add_argument("--limit", type=int, default=0, help="stream only the first N images")
    ap.add_argument("--frame-id-base", type=int,
                    help="frame ids BASE, BASE+1, ...: exactly-once delivery when the stream resumes")
    ap.add_argument("--camera", metavar="FX,FY,CX,CY[,K1,K2,P1,P2,K3]",
                    help="intrinsics for a new session (--create): verified loops then carry a relative pose")
    ap.add_argument("--no-verify", action="store_true", help="descriptor ranking only")
    ap.add_argument("--retry-seconds", type=float, default=120, help="give up after this long without progress")
    ap.add_argument("--summary", help="write a JSON summary here (frame ids, best matches, reconnects)")
    ap.add_argument("--require-matches-from", metavar="ROBOT",
                    help="exit 1 unless most frames' best match is a frame of ROBOT (for CI)")
    a = ap.parse_args()

    key = pathlib.Path(a.key_file).read_text().strip() if a.key_file else os.environ.get("LOOPD_KEY")
    files = sorted(p for p in pathlib.Path(a.folder).iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    files = files[: a.limit] if a.limit else files
    if not files:
        sys.exit(f"no images in {a.folder}")

    client = Client(a.server, key=key, ca=a.ca, retry=RetryPolicy(deadline=a.retry_seconds))
    client.wait_ready(timeout=a.retry_seconds)
    if a.create:
        camera = [float(x) for x in a.camera.split(",")] if a.camera else None
        client.create_session(a.session, camera=camera, exist_ok=True)

    def frames():
        t0 = time.time()
        for i, path in enumerate(files):
            if a.fps > 0:
                time.sleep(max(0.0, t0 + i / a.fps - time.time()))
            yield Frame(image=path.read_bytes(), timestamp=time.time(),
                        frame_id=None if a.frame_id_base is None else a.frame_id_base + i,
                        metadata_json=json.dumps({"file": path.name}))

    options = query_options(k=a.k, scope=a.scope, exclude_last_frames=a.exclude_last, verify=not a.no_verify)
    acked, best, from_robot, failed, verified = [], [], 0, 0, 0
    for answer in client.stream(a.session, a.robot, frames(), options):
        name = answer.frame.metadata_json
        if answer.error_code:
            failed += 1
            print(f"{name}: error {answer.error_code}: {answer.error}", flush=True)
            continue
        acked.append(answer.frame_id)
        if not answer.matches:
            best.append(None)
            print(f"{name}: frame {answer.frame_id}, no loop candidates", flush=True)
            continue
        top = answer.matches[0]
        best.append({"robot": top.robot_id, "frame_id": top.frame_id, "score": top.score,
                     "verified": top.verification.verified})
        from_robot += top.robot_id == a.require_matches_from
        verified += top.verification.verified
        print(f"{name}: frame {answer.frame_id}, candidates {', '.join(describe(m) for m in answer.matches)}",
              flush=True)
    print(f"{len(files)} frames streamed, {failed} failed, {verified} verified loops, "
          f"{client.retries} retries", flush=True)
    if a.summary:
        pathlib.Path(a.summary).write_text(json.dumps(
            {"robot": a.robot, "acked": acked, "best": best, "failed": failed, "retries": client.retries}))
    if failed:
        sys.exit(1)
    if a.require_matches_from and from_robot * 2 < len(files):
        sys.exit(f"only {from_robot}/{len(files)} best matches were frames of {a.require_matches_from}")


if __name__ == "__main__":
    main()
