"""When and how long to wait before trying a call again."""
from __future__ import annotations

import random
import time
from dataclasses import dataclass
from typing import Callable, TypeVar

import grpc

T = TypeVar("T")

# The server says "not now" with these: a restart or a storage fault (UNAVAILABLE), a full queue
# or a tenant's rate limit (RESOURCE_EXHAUSTED). Everything else is an answer, not a hiccup.
RETRYABLE = (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.RESOURCE_EXHAUSTED)
# A write also after its deadline passed: it may have been stored, and its frame id or
# idempotency key makes the retry answer that frame instead of storing it again.
RETRYABLE_WRITE = RETRYABLE + (grpc.StatusCode.DEADLINE_EXCEEDED,)


@dataclass
class RetryPolicy:
    """Exponential backoff with full jitter, capped, for at most `deadline` seconds in all."""

    initial: float = 0.1
    maximum: float = 5.0
    multiplier: float = 2.0
    deadline: float = 120.0

    def delays(self):
        """Sleep lengths until the deadline is spent (then the generator ends)."""
        start = time.monotonic()
        ceiling = self.initial
        while True:
            delay = random.uniform(0, ceiling)
            if time.monotonic() + delay - start > self.deadline:
                return
            yield delay
            ceiling = min(self.maximum, ceiling * self.multiplier)


NO_RETRY = RetryPolicy(deadline=0.0)


def retrying(policy: RetryPolicy, call: Callable[[], T], on_retry: Callable[[grpc.RpcError], None],
             codes=RETRYABLE) -> T:
    """`call()`, tried again after a backoff while it fails with a status in `codes`."""
    delays = policy.delays()
    while True:
        try:
            return call()
        except grpc.RpcError as e:
            if e.code() not in codes:
                raise
            delay = next(delays, None)
            if delay is None:
                raise
            on_retry(e)
            time.sleep(delay)
