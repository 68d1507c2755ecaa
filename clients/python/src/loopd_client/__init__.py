"""Python client for loopd, the networked loop-closure detector.

    from loopd_client import Client, Frame, query_options
    with Client("loopd.example:50051", key=KEY, ca="ca.pem") as c:
        c.create_session("warehouse", exist_ok=True)
        for answer in c.stream("warehouse", "robot-1", frames, query_options(k=3, scope="other")):
            ...
"""
from ._gen.loopd.v1 import loopd_pb2 as pb
from .client import Client, query_options
from .retry import NO_RETRY, RETRYABLE, RetryPolicy
from .stream import Answer, Frame, StreamBroken

__all__ = ["Client", "Frame", "Answer", "RetryPolicy", "NO_RETRY", "RETRYABLE", "StreamBroken", "pb",
           "query_options"]
