"""A frame stream that survives server restarts: frames not yet answered are sent again on a new
call, in order, after a backoff; the caller sees one answer per frame, in order."""
from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Deque, Iterable, Iterator, List, Optional

import grpc

from ._gen.loopd.v1 import loopd_pb2 as pb
from .retry import RETRYABLE, RetryPolicy

ALREADY_EXISTS = grpc.StatusCode.ALREADY_EXISTS.value[0]


@dataclass
class Frame:
    """One keyframe: an encoded image (JPEG, PNG, ...) or a descriptor. Give `frame_id` (unique in
    the session) for exactly-once delivery across retries and reconnects, or let the server assign
    one: the client then sends a key of its own with the frame (a UUID, or `idempotency_key` when
    given), and a frame sent again with the key of a stored frame is answered that frame's id and
    stores nothing, on the embedded store and on a cluster, through any node."""

    image: Optional[bytes] = None
    descriptor: Optional[List[float]] = None
    timestamp: Optional[float] = None
    frame_id: Optional[int] = None
    pose: Optional[pb.Pose] = None
    metadata_json: str = ""
    idempotency_key: Optional[str] = None
    # A depth image registered to `image` (16-bit PNG/PGM/TIFF in the session camera's
    # depth_scale units per metre, or float TIFF in metres): its verified loops get metric poses.
    depth: Optional[bytes] = None
    # The right image of a stereo pair (a session camera with `stereo`): the same metric poses.
    right: Optional[bytes] = None


@dataclass
class Answer:
    """The server's answer to one streamed frame. `error_code` (a gRPC code number) and `error`
    are set when that frame was refused; the stream goes on. `resent`: the frame was sent again
    after a reconnect; if the lost call had already stored it (ALREADY_EXISTS for a frame with an
    id), it counts as acknowledged and its candidates, lost with that call, are empty."""

    frame: Frame
    frame_id: int
    matches: List[pb.Match] = field(default_factory=list)
    error_code: int = 0
    error: str = ""
    resent: bool = False


class StreamBroken(Exception):
    """The stream could not be resumed within the retry policy's deadline."""


class _Pending:
    __slots__ = ("frame", "request", "seq", "resent")

    def __init__(self, frame: Frame, request: pb.AddFrameRequest, seq: int):
        self.frame, self.request, self.seq, self.resent = frame, request, seq, False


class ResumableStream:
    """Feeds frames to successive StreamFrames calls; at most `window` frames are unanswered."""

    def __init__(self, frames: Iterable[Frame], build: Callable[[Frame], pb.AddFrameRequest], window: int):
        self._source = iter(frames)
        self._build = build
        self._window = max(1, window)
        self._pending: Deque[_Pending] = collections.deque()
        self._cond = threading.Condition()
        self._pull = threading.Lock()  # one generator reads the caller's iterator at a time
        self._generation = 0
        self._next_seq = 0
        self._source_done = False
        self.reconnects = 0

    def run(self, open_call: Callable[[Iterator[pb.AddFrameRequest]], Iterator[pb.AddAndQueryResponse]],
            policy: RetryPolicy, on_retry: Callable[[Optional[grpc.RpcError]], None]) -> Iterator[Answer]:
        delays = policy.delays()
        try:
            while True:
                call = open_call(self._requests(self._open_generation()))
                error: Optional[grpc.RpcError] = None
                try:
                    for response in call:
                        yield self._answered(response)
                        delays = policy.delays()  # progress: the next outage gets a full deadline
                    if self._finished():
                        return
                except grpc.RpcError as e:
                    if e.code() not in RETRYABLE:
                        raise
                    error = e
                finally:
                    call.cancel()
                delay = next(delays, None)
                if delay is None:
                    raise StreamBroken(f"stream not resumed within {policy.deadline} s: {error}") from error
                on_retry(error)
                self.reconnects += 1
                time.sleep(delay)
        finally:
            with self._cond:
                self._generation = -1  # stops any request generator still running
                self._cond.notify_all()

    def _open_generation(self) -> int:
        with self._cond:
            self._generation += 1
            for p in self._pending:
                p.resent = True
            self._cond.notify_all()
            return self._generation

    def _finished(self) -> bool:
        with self._cond:
            return self._source_done and not self._pending

    def _answered(self, response: pb.AddAndQueryResponse) -> Answer:
        with self._cond:
            if not self._pending:
                raise StreamBroken("the server answered a frame that was never sent")
            p = self._pending.popleft()
            self._cond.notify_all()
        if p.resent and response.error_code == ALREADY_EXISTS and p.frame.frame_id is not None:
            return Answer(p.frame, p.frame.frame_id, resent=True)
        return Answer(p.frame, response.frame_id, list(response.matches), response.error_code,
                      response.error, p.resent)

    def _requests(self, generation: int) -> Iterator[pb.AddFrameRequest]:
        with self._cond:
            next_seq = self._pending[0].seq if self._pending else self._next_seq
        while True:
            with self._cond:
                while True:
                    if self._generation != generation:
                        return
                    if self._pending and next_seq - self._pending[0].seq < len(self._pending):
                        item = self._pending[max(0, next_seq - self._pending[0].seq)]
                        next_seq = item.seq + 1
                        break
                    if self._source_done:
                        return  # everything sent: half-close, answers still come
                    if len(self._pending) < self._window:
                        item = None
                        break
                    self._cond.wait(0.5)
            if item is None:
                item = self._pull_one(generation, next_seq)
                if item is None:
                    continue  # source ended, another generator queued a frame, or this call was replaced
                next_seq = item.seq + 1
            yield item.request

    def _pull_one(self, generation: int, next_seq: int) -> Optional[_Pending]:
        with self._pull:
            with self._cond:
                if self._source_done or self._generation != generation or self._next_seq != next_seq:
                    return None
            try:
                frame = next(self._source)
            except StopIteration:
                with self._cond:
                    self._source_done = True
                    self._cond.notify_all()
                return None
            request = self._build(frame)
            with self._cond:
                item = _Pending(frame, request, self._next_seq)
                self._next_seq += 1
                self._pending.append(item)
                self._cond.notify_all()
                # A replaced call's generator leaves the frame queued for the live one.
                return item if self._generation == generation else None
