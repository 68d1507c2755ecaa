"""The Python client against a real `loopd serve` with TLS and keys, on real corridor frames."""
from __future__ import annotations

import threading
import time

import grpc
import pytest
from conftest import Server, corridor, corridor_truth

from loopd_client import Client, Frame, RetryPolicy, query_options

REFS = 40


def test_tls_key_stream_and_query_find_the_known_places(server):
    key = server.tenant("fleet")
    with Client(server.grpc, key=key, ca=server.ca) as c:
        c.create_session("corridor", exist_ok=True)
        again = c.create_session("corridor", exist_ok=True)
        assert again.id == "corridor"
        frames = [Frame(image=img, timestamp=float(i), frame_id=i) for i, img in enumerate(corridor("ref", REFS))]
        answers = list(c.stream("corridor", "mapper", frames, query_options(verify=False)))
        assert [a.frame_id for a in answers] == list(range(REFS))
        assert all(a.error_code == 0 for a in answers)
        assert c.get_session("corridor").frames == REFS

        truth = corridor_truth()
        hits = 0
        for q, img in enumerate(corridor("query", 20)):
            matches = c.query("corridor", "visitor", image=img, options=query_options(k=1, verify=False))
            hits += matches[0].frame_id in truth[q]
        # The plain backbone on corridor: most first candidates are the right place.
        assert hits >= 14, f"{hits}/20 first candidates in the ground truth"

        response = c.add_and_query("corridor", "visitor", Frame(image=corridor("query", 1)[0], frame_id=5000),
                                   query_options(k=3, scope="other", verify=False))
        assert response.frame_id == 5000
        assert response.matches[0].robot_id == "mapper"
        assert response.matches[0].frame_id in truth[0]
        # Every candidate answered is kept: the visitor's three, with the same scores.
        kept = {(l.query_frame, l.match_frame): l for l in c.loops("corridor", robot="visitor")}
        assert set(kept) == {(5000, m.frame_id) for m in response.matches}
        judged = c.set_verdict("corridor", 5000, response.matches[0].frame_id, True,
                               covariance=[0.01 if i % 7 == 0 else 0.0 for i in range(36)])
        assert judged.verdict.accepted and len(judged.verdict.covariance) == 36
        assert sum(1 for _ in c.loops("corridor", page=7)) >= 10  # the mapper's stream answered candidates too
        assert c.retries == 0


def test_bad_and_foreign_keys_are_refused_without_retries(server):
    owner, other = server.tenant("owner"), server.tenant("other")
    with Client(server.grpc, key=owner, ca=server.ca) as c:
        dim = c.create_session("private", exist_ok=True).dim
        c.add_frame("private", "r", Frame(descriptor=[1.0] * dim, timestamp=1.0))
    for key, code in [(None, grpc.StatusCode.UNAUTHENTICATED),
                      ("lpd_000000000000_" + "0" * 64, grpc.StatusCode.UNAUTHENTICATED),
                      (other, grpc.StatusCode.NOT_FOUND)]:
        with Client(server.grpc, key=key, ca=server.ca) as c:
            with pytest.raises(grpc.RpcError) as e:
                c.get_session("private")
            assert e.value.code() == code
            assert c.retries == 0
    with Client(server.grpc, key=owner, ca=server.ca) as c:
        assert c.get_session("private").frames == 1


def test_tenants_are_managed_with_the_admin_key(server):
    from conftest import ADMIN_KEY
    with Client(server.grpc, key=ADMIN_KEY, ca=server.ca) as admin:
        tenant, key = admin.create_tenant("py-admin", rate=100.0, max_in_flight=3)
        assert tenant.limits.max_in_flight == 3 and key.startswith("lpd_")
        assert any(t.name == "py-admin" and not t.revoked for t in admin.list_tenants())
        with Client(server.grpc, key=key, ca=server.ca) as robot:
            robot.create_session("mine", exist_ok=True)
            with pytest.raises(grpc.RpcError) as e:
                robot.list_tenants()
            assert e.value.code() == grpc.StatusCode.PERMISSION_DENIED
            assert admin.revoke_tenant("py-admin").revoked
            with pytest.raises(grpc.RpcError) as e:
                robot.list_sessions()
            assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED


def test_untrusted_server_certificate_is_refused(server, tmp_path):
    from conftest import make_certs
    make_certs(tmp_path)  # another CA
    with Client(server.grpc, key=server.tenant("nobody"), ca=tmp_path / "ca.pem",
                retry=RetryPolicy(deadline=1.0)) as c:
        with pytest.raises(grpc.RpcError) as e:
            c.list_sessions()
        assert e.value.code() == grpc.StatusCode.UNAVAILABLE


def test_rate_limited_writes_are_retried_until_stored(server):
    key = server.tenant("slow", rate=5.0)
    with Client(server.grpc, key=key, ca=server.ca) as c:
        dim = c.create_session("rated", exist_ok=True).dim
        start = time.monotonic()
        ids = [c.add_frame("rated", "r", Frame(descriptor=[float(i % 7 + 1)] + [1.0] * (dim - 1), timestamp=float(i)))
               for i in range(25)]
        elapsed = time.monotonic() - start
        assert len(set(ids)) == 25
        assert c.retries > 0, "25 writes at 5/s never hit the limit"
        assert elapsed > 2.0, f"25 writes at 5/s took {elapsed:.1f} s"
        assert c.get_session("rated").frames == 25


def test_stream_resumes_after_a_server_restart_exactly_once(tmp_path):
    server = Server(tmp_path)
    try:
        key = server.tenant("robots")
        with Client(server.grpc, key=key, ca=server.ca) as c:
            c.create_session("restart", exist_ok=True)
            images = corridor("ref", 60)

            def frames():
                for i, img in enumerate(images):
                    if i == 25:
                        threading.Thread(target=server.restart).start()  # SIGKILL mid-stream
                    time.sleep(0.05)
                    yield Frame(image=img, timestamp=float(i), frame_id=100 + i)

            answers = list(c.stream("restart", "mapper", frames(), query_options(verify=False), window=8))
            assert [a.frame_id for a in answers] == [100 + i for i in range(60)]
            assert all(a.error_code == 0 for a in answers), [a.error for a in answers if a.error_code]
            assert c.retries > 0, "the stream never had to reconnect"
            assert any(a.resent for a in answers)
            # Exactly once: every acknowledged frame is stored, none twice.
            assert c.get_session("restart").frames == 60
            for i in (0, 24, 25, 30, 59):  # a query on a frame id that is not stored is NOT_FOUND
                c.query("restart", "mapper", frame_id=100 + i, options=query_options(k=1, verify=False))
    finally:
        server.stop()


def test_calls_wait_for_a_server_that_is_starting(tmp_path):
    server = Server(tmp_path)
    key = server.tenant("patient")
    server.kill()
    try:
        with Client(server.grpc, key=key, ca=server.ca, retry=RetryPolicy(deadline=120)) as c:
            threading.Timer(1.0, lambda: server.start(wait=False)).start()
            assert c.create_session("later", exist_ok=True).id == "later"
            assert c.retries > 0
    finally:
        time.sleep(1.5)
        server.stop()


def test_index_kind_on_create_and_the_approximate_index_catches_up(server):
    """`index` reaches the server; an approximate session reports the frames its index covers
    and answers the corridor's queries with the same places as an exact one; a wrong kind is
    refused before anything is sent."""
    from loopd_client import pb
    key = server.tenant("indexes")
    with Client(server.grpc, key=key, ca=server.ca) as c:
        with pytest.raises(ValueError, match="not one of"):
            c.create_session("bad", index="fast")
        kinds = {"exact": pb.INDEX_KIND_EXACT, "approximate": pb.INDEX_KIND_APPROXIMATE}
        for name, kind in kinds.items():
            assert c.create_session(name, index=name).index == kind
            frames = [Frame(image=img, timestamp=float(i), frame_id=i) for i, img in enumerate(corridor("ref", 20))]
            assert len(list(c.stream(name, "mapper", frames, query_options(verify=False)))) == 20
        assert not c.get_session("exact").HasField("approximate_frames")
        deadline = time.time() + 30
        while c.get_session("approximate").approximate_frames != 20:
            assert time.time() < deadline, c.get_session("approximate")
            time.sleep(0.05)
        assert c.create_session("auto").index == pb.INDEX_KIND_AUTO
        for img in corridor("query", 5):
            found = [[m.frame_id for m in c.query(name, "visitor", image=img, options=query_options(k=3, verify=False))]
                     for name in kinds]
            assert found[0] == found[1]


def test_a_frame_the_client_sends_again_is_stored_once(server):
    """A frame with a server-assigned id carries a key of the client's own: the same request sent
    again (as the client's retries send it, after a timeout or an UNAVAILABLE) answers the first
    frame's id and stores nothing; the next frame gets a key of its own."""
    key = server.tenant("retrying")
    with Client(server.grpc, key=key, ca=server.ca) as c:
        c.create_session("twice", exist_ok=True)
        images = corridor("ref", 2)
        request = c.frame_request("twice", "r", Frame(image=images[0], timestamp=1.0), query_options(verify=False))
        assert len(request.idempotency_key) == 32, request.idempotency_key
        first = c._write(c._stub.AddAndQuery, request)
        again = c._write(c._stub.AddAndQuery, request)
        assert again.frame_id == first.frame_id
        assert c.get_session("twice").frames == 1
        second = c.add_frame("twice", "r", Frame(image=images[1], timestamp=2.0))
        assert second != first.frame_id and c.get_session("twice").frames == 2
        # A key the caller gives is sent as it is.
        mine = c.frame_request("twice", "r", Frame(image=images[0], timestamp=3.0, idempotency_key="robot-r/3"))
        assert mine.idempotency_key == "robot-r/3"


def test_rgbd_frames_give_metric_loops(server):
    """Depth images reach the server with frames and queries (`Frame.depth`, `query(depth=)`,
    `create_session(depth_scale=)`): tum-desk's frame 5 closes on a frame sent with depth with a
    metric pose and its covariance; bad depth is refused with INVALID_ARGUMENT."""
    from conftest import DATA
    desk = DATA / "rgbd-slambook2/tum-desk"
    color = lambda i: (desk / f"color/{i}.png").read_bytes()  # noqa: E731
    depth = lambda i: (desk / f"depth/{i}.pgm").read_bytes()  # noqa: E731
    key = server.tenant("rgbd")
    with Client(server.grpc, key=key, ca=server.ca) as c:
        c.create_session("desk", camera=[518.0, 519.0, 325.5, 253.5], depth_scale=1000.0)
        for i in range(1, 5):
            c.add_frame("desk", "rgbd", Frame(image=color(i), depth=depth(i), timestamp=float(i), frame_id=i))
        with pytest.raises(grpc.RpcError) as bad:
            c.add_frame("desk", "rgbd", Frame(image=color(5), depth=color(5), timestamp=5.0, frame_id=5))
        assert bad.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "16-bit" in bad.value.details()
        assert c.get_session("desk").frames == 4
        best = c.query("desk", "other", image=color(5), options=query_options(k=1))[0]
        v = best.verification
        assert v.verified and v.metric and len(v.covariance) == 36 and v.pose_inliers >= 30, v
        # Frame 5 is 0.23 m from frame 4 (the ground truth), and the pose says so in metres.
        t = (v.relative_pose.tx ** 2 + v.relative_pose.ty ** 2 + v.relative_pose.tz ** 2) ** 0.5
        assert best.frame_id == 4 and abs(t - 0.232) < 0.05, (best.frame_id, t)
        with_depth = c.query("desk", "other", image=color(5), depth=depth(5), options=query_options(k=1))[0]
        assert with_depth.verification.metric


def test_stereo_frames_give_metric_loops(server):
    """EuRoC's calibrated stereo pair (`create_session(stereo=...)`, `Frame.right`): frame 1
    closes on frame 0, sent with its right image, with a metric pose near the ground truth's 0.43 m."""
    from conftest import DATA, euroc_stereo

    camera, stereo = euroc_stereo()
    img = lambda side, i: (DATA / f"euroc-lcd/{side}_img_{i}.png").read_bytes()  # noqa: E731
    key = server.tenant("stereo")
    with Client(server.grpc, key=key, ca=server.ca) as c:
        c.create_session("euroc", camera=camera, stereo=stereo)
        c.add_frame("euroc", "mav", Frame(image=img("left", 0), right=img("right", 0), timestamp=0.0, frame_id=0))
        best = c.query("euroc", "other", image=img("left", 1), options=query_options(k=1))[0]
        v = best.verification
        assert best.frame_id == 0 and v.verified and v.metric and len(v.covariance) == 36, v
        norm = (v.relative_pose.tx ** 2 + v.relative_pose.ty ** 2 + v.relative_pose.tz ** 2) ** 0.5
        assert abs(norm - 0.432) < 0.1, norm


def test_sessions_name_their_model_among_the_served_ones(tmp_path):
    """A server with `--models` (two TorchScript models exported here with the venv's torch):
    `models()` lists them after the built-in one, sessions bound to each take images and find
    their own frames, and a name the server does not serve is refused."""
    import subprocess
    import sys
    from conftest import DATA, REPO
    repo = tmp_path / "models"
    subprocess.run([sys.executable, str(REPO / "tests/reference/script_models.py"), "export", str(tmp_path / "all")],
                   check=True)
    repo.mkdir()
    for name in ("small-resnet", "small-bgr"):
        (tmp_path / "all" / name).rename(repo / name)
    (tmp_path / "server").mkdir()
    server = Server(tmp_path / "server", extra=("--models", str(repo)))
    try:
        key = server.tenant("models")
        with Client(server.grpc, key=key, ca=server.ca) as c:
            models = c.models()
            assert [(m.name, m.default, m.dim) for m in models][1:] == [("small-bgr", False, 256),
                                                                         ("small-resnet", False, 512)]
            assert models[0].default and models[0].kind == "builtin"
            with pytest.raises(grpc.RpcError) as e:
                c.create_session("x", model="netvlad")
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "small-resnet" in e.value.details()
            images = [(DATA / p).read_bytes() for p in ("slambook2-ch11/1.png", "photos/dog.jpg", "photos/scream.jpg")]
            for model in ("small-resnet", "small-bgr", ""):
                s = c.create_session(f"s-{model or 'default'}", model=model)
                assert s.model == (model or models[0].name)
                assert s.descriptor_id == next(m.descriptor_id for m in models if m.name == s.model)
                frames = [Frame(image=img, timestamp=float(i), frame_id=i) for i, img in enumerate(images)]
                assert len(list(c.stream(s.id, "mapper", frames, query_options(verify=False)))) == 3
                found = c.query(s.id, "visitor", image=images[1], options=query_options(k=1, verify=False))
                assert found[0].frame_id == 1 and found[0].score > 0.999, found
    finally:
        server.stop()
