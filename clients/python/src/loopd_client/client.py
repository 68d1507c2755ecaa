"""The loopd gRPC client: TLS and an API key, retries with backoff, resumable frame streams."""
from __future__ import annotations

import pathlib
import time
import uuid
from typing import Iterable, Iterator, List, Optional, Sequence, Tuple, Union

import grpc

from ._gen.loopd.v1 import loopd_pb2 as pb
from ._gen.loopd.v1 import loopd_pb2_grpc as rpc
from .retry import RETRYABLE_WRITE, RetryPolicy, retrying
from .stream import Answer, Frame, ResumableStream

PemSource = Union[bytes, str, pathlib.Path, None]
SCOPES = {"all": pb.SCOPE_ALL, "same": pb.SCOPE_SAME_ROBOT, "other": pb.SCOPE_OTHER_ROBOTS}


def _pem(source: PemSource) -> Optional[bytes]:
    if source is None or isinstance(source, bytes):
        return source
    return pathlib.Path(source).read_bytes()


def query_options(k: Optional[int] = None, scope: str = "", **fields) -> pb.QueryOptions:
    """QueryOptions from keywords (`k=3, scope="other", verify=False, exclude_last_frames=10`,
    any field of proto's QueryOptions); unset fields take the session's defaults."""
    options = pb.QueryOptions(**fields)
    if k is not None:
        options.k = k
    if scope:
        options.scope = SCOPES[scope]
    return options


class Client:
    """One channel to a loopd server.

    `target` is host:port of its gRPC address. TLS is on when `ca` (the server's CA, PEM bytes or
    a file) or `tls=True` (system roots) is given; `client_cert`/`client_key` add a client
    certificate (mTLS). `key` is the tenant's API key. Unary calls and streams are retried with
    `retry` on UNAVAILABLE and RESOURCE_EXHAUSTED; `timeout` bounds each unary attempt.
    """

    def __init__(self, target: str, *, key: Optional[str] = None, ca: PemSource = None, tls: bool = False,
                 client_cert: PemSource = None, client_key: PemSource = None,
                 server_name: Optional[str] = None, retry: Optional[RetryPolicy] = None,
                 timeout: float = 60.0):
        options = [("grpc.max_receive_message_length", 64 << 20), ("grpc.keepalive_time_ms", 30_000)]
        if server_name:
            options.append(("grpc.ssl_target_name_override", server_name))
        if ca is not None or tls or client_cert is not None:
            credentials = grpc.ssl_channel_credentials(
                root_certificates=_pem(ca), private_key=_pem(client_key), certificate_chain=_pem(client_cert))
            self._channel = grpc.secure_channel(target, credentials, options)
        else:
            self._channel = grpc.insecure_channel(target, options)
        self._stub = rpc.LoopdStub(self._channel)
        self._admin = rpc.AdminStub(self._channel)
        self._metadata = [("authorization", f"Bearer {key}")] if key else []
        self.retry = retry or RetryPolicy()
        self.timeout = timeout
        self.retries = 0  # calls tried again (and stream reconnects) so far

    def close(self) -> None:
        self._channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def wait_ready(self, timeout: float = 60.0) -> None:
        grpc.channel_ready_future(self._channel).result(timeout=timeout)

    def _count_retry(self, _error) -> None:
        self.retries += 1

    def _unary(self, method, request):
        return retrying(self.retry, lambda: method(request, metadata=self._metadata, timeout=self.timeout),
                        self._count_retry)

    # Sessions.
    def create_session(self, id: str = "", name: str = "", *, camera: Optional[Sequence[float]] = None,
                       storage: int = pb.STORAGE_UNSPECIFIED, default_query: Optional[pb.QueryOptions] = None,
                       thumbnails: bool = False, index: str = "auto", exist_ok: bool = False,
                       depth_scale: Optional[float] = None, stereo: Optional[dict] = None,
                       model: str = "") -> pb.Session:
        """A new session; `camera` is fx, fy, cx, cy[, k1, k2, p1, p2, k3] (verified loops then
        carry a relative pose); `depth_scale`: units per metre of its frames' 16-bit depth images
        (default 1000); `stereo`: the right camera of a stereo pair, {"baseline": m} for a rectified
        pair or {"rotation": 9 values, "translation": 3, "right_intrinsics": 4, "right_distortion":
        5} (X_right = R X_left + t); `thumbnails` keeps a small JPEG of each frame (the loop
        inspector shows them); `index` is "auto" (exact until the session is large, then
        approximate), "exact" or "approximate"; `model` names the served model whose descriptors
        it holds (`models()`; empty: the server's default). With `exist_ok` an existing session of
        that id is returned."""
        kinds = {"auto": pb.INDEX_KIND_AUTO, "exact": pb.INDEX_KIND_EXACT, "approximate": pb.INDEX_KIND_APPROXIMATE}
        if index not in kinds:
            raise ValueError(f"index {index!r} is not one of {', '.join(kinds)}")
        request = pb.CreateSessionRequest(id=id, name=name or id, storage=storage, default_query=default_query,
                                          thumbnails=thumbnails, index=kinds[index], model=model)
        if camera is not None:
            v = [float(x) for x in camera]
            request.camera.CopyFrom(pb.Camera(fx=v[0], fy=v[1], cx=v[2], cy=v[3], distortion=v[4:]))
            if depth_scale is not None:
                request.camera.depth_scale = float(depth_scale)
            if stereo is not None:
                request.camera.stereo.CopyFrom(pb.StereoCamera(**stereo))
        try:
            return self._unary(self._stub.CreateSession, request)
        except grpc.RpcError as e:
            if exist_ok and id and e.code() == grpc.StatusCode.ALREADY_EXISTS:
                return self.get_session(id)
            raise

    def models(self) -> List[pb.Model]:
        """The models the server serves (`serve --models`), the default first."""
        return list(self._unary(self._stub.ListModels, pb.ListModelsRequest()).models)

    def get_session(self, id: str) -> pb.Session:
        return self._unary(self._stub.GetSession, pb.GetSessionRequest(id=id))

    def list_sessions(self) -> List[pb.Session]:
        return list(self._unary(self._stub.ListSessions, pb.ListSessionsRequest()).sessions)

    def delete_session(self, id: str) -> None:
        self._unary(self._stub.DeleteSession, pb.DeleteSessionRequest(id=id))

    # Tenants (the admin key).
    def create_tenant(self, name: str, *, max_sessions: Optional[int] = None, max_frames: Optional[int] = None,
                      rate: Optional[float] = None, max_in_flight: Optional[int] = None) -> Tuple[pb.Tenant, str]:
        """A tenant and its key (shown once). An existing tenant gets a new key (rotation)."""
        limits = pb.TenantLimits(max_sessions=max_sessions, max_frames=max_frames, rate=rate,
                                 max_in_flight=max_in_flight)
        r = self._unary(self._admin.CreateTenant, pb.CreateTenantRequest(name=name, limits=limits))
        return r.tenant, r.key

    def list_tenants(self) -> List[pb.Tenant]:
        return list(self._unary(self._admin.ListTenants, pb.ListTenantsRequest()).tenants)

    def revoke_tenant(self, name_or_key_id: str) -> pb.Tenant:
        return self._unary(self._admin.RevokeTenant, pb.RevokeTenantRequest(name_or_key_id=name_or_key_id))

    # Frames.
    def frame_request(self, session: str, robot: str, frame: Frame,
                      options: Optional[pb.QueryOptions] = None) -> pb.AddFrameRequest:
        request = pb.AddFrameRequest(
            session_id=session, robot_id=robot,
            timestamp=frame.timestamp if frame.timestamp is not None else time.time(),
            metadata_json=frame.metadata_json, options=options)
        if frame.frame_id is not None:
            request.frame_id = frame.frame_id
        if frame.idempotency_key is not None:
            request.idempotency_key = frame.idempotency_key
        elif frame.frame_id is None:
            # A server-assigned id: a key of its own makes every retry of this request (the same
            # request object is sent again) store the frame once.
            request.idempotency_key = uuid.uuid4().hex
        if frame.pose is not None:
            request.pose.CopyFrom(frame.pose)
        if frame.image is not None:
            request.image = frame.image
            if frame.depth is not None:
                request.depth = frame.depth
            if frame.right is not None:
                request.right = frame.right
        elif frame.descriptor is not None:
            request.descriptor.values.extend(frame.descriptor)
        else:
            raise ValueError("a frame needs an image or a descriptor")
        return request

    def _write(self, method, request: pb.AddFrameRequest):
        """A write, retried (after its deadline too: it carries a frame id or an idempotency key);
        with a frame id an ALREADY_EXISTS after a retry means an earlier attempt was stored
        (exactly once), so it is answered as success."""
        attempts = 0

        def attempt():
            nonlocal attempts
            attempts += 1
            return method(request, metadata=self._metadata, timeout=self.timeout)

        try:
            return retrying(self.retry, attempt, self._count_retry, RETRYABLE_WRITE)
        except grpc.RpcError as e:
            if attempts > 1 and request.HasField("frame_id") and e.code() == grpc.StatusCode.ALREADY_EXISTS:
                return None
            raise

    def add_frame(self, session: str, robot: str, frame: Frame) -> int:
        """Stores a frame; its id."""
        response = self._write(self._stub.AddFrame, self.frame_request(session, robot, frame))
        return frame.frame_id if response is None else response.frame_id

    def add_and_query(self, session: str, robot: str, frame: Frame,
                      options: Optional[pb.QueryOptions] = None) -> pb.AddAndQueryResponse:
        """Stores a frame and answers its loop candidates among the frames before it."""
        response = self._write(self._stub.AddAndQuery, self.frame_request(session, robot, frame, options))
        return pb.AddAndQueryResponse(frame_id=frame.frame_id) if response is None else response

    def query(self, session: str, robot: str, *, image: Optional[bytes] = None,
              descriptor: Optional[Sequence[float]] = None, frame_id: Optional[int] = None,
              options: Optional[pb.QueryOptions] = None, timestamp: Optional[float] = None,
              depth: Optional[bytes] = None, right: Optional[bytes] = None) -> List[pb.Match]:
        """Loop candidates for an image (with its depth image, if given), a descriptor or a
        stored frame (nothing is stored)."""
        request = pb.QueryRequest(session_id=session, robot_id=robot, options=options)
        if image is not None:
            request.image = image
            if depth is not None:
                request.depth = depth
            if right is not None:
                request.right = right
        elif descriptor is not None:
            request.descriptor.values.extend(descriptor)
        elif frame_id is not None:
            request.frame_id = frame_id
        else:
            raise ValueError("query needs an image, a descriptor or a frame id")
        if timestamp is not None:
            request.timestamp = timestamp
        return list(self._unary(self._stub.Query, request).matches)

    def loops(self, session: str, *, robot: str = "", min_score: Optional[float] = None,
              verified: Optional[bool] = None, time_from: Optional[float] = None,
              time_to: Optional[float] = None, min_confidence: Optional[float] = None,
              page: int = 500) -> Iterator[pb.Loop]:
        """Every kept loop candidate of a session matching the filters, in frame order (pages
        fetched as needed); `min_confidence` keeps those answered with at least that calibrated
        confidence (each Loop's `confidence`; Match has it too)."""
        after = ""
        while True:
            request = pb.ListLoopsRequest(session_id=session, robot_id=robot, min_score=min_score,
                                          verified=verified, time_from=time_from, time_to=time_to,
                                          min_confidence=min_confidence, after=after, limit=page)
            response = self._unary(self._stub.ListLoops, request)
            yield from response.loops
            if not response.next:
                return
            after = response.next

    def set_verdict(self, session: str, query_frame: int, match_frame: int, accepted: bool, *,
                    relative_pose: Optional[pb.RelativePose] = None,
                    covariance: Optional[Sequence[float]] = None) -> pb.Loop:
        """Accepts or rejects a kept loop, optionally with the client's own relative pose and 6x6
        covariance (row-major)."""
        request = pb.SetLoopVerdictRequest(session_id=session, query_frame=query_frame, match_frame=match_frame,
                                           accepted=accepted, relative_pose=relative_pose,
                                           covariance=list(covariance or []))
        return self._unary(self._stub.SetLoopVerdict, request)

    def thumbnail(self, session: str, frame_id: int) -> bytes:
        """A frame's thumbnail (JPEG) in a session created with `thumbnails`."""
        return self._unary(self._stub.GetThumbnail, pb.GetThumbnailRequest(session_id=session, frame_id=frame_id)).jpeg

    def stream(self, session: str, robot: str, frames: Iterable[Frame],
               options: Optional[pb.QueryOptions] = None, window: int = 64) -> Iterator[Answer]:
        """Streams frames (StreamFrames) and yields one Answer per frame, in order. After a lost
        connection or a server restart the frames not yet answered are sent again on a new call
        (see Frame.frame_id for exactly-once); at most `window` frames wait for their answer."""
        stream = ResumableStream(frames, lambda f: self.frame_request(session, robot, f, options), window)
        yield from stream.run(lambda requests: self._stub.StreamFrames(requests, metadata=self._metadata),
                              self.retry, self._count_retry)
