"""A real `loopd serve` (target/release/loopd) on loopback with TLS and keys, for the client tests.
Certificates are made at run time with openssl; nothing secret is committed."""
from __future__ import annotations

import json
import os
import pathlib
import signal
import socket
import ssl
import subprocess
import time
import urllib.request

import pytest

REPO = pathlib.Path(__file__).resolve().parents[3]
BIN = pathlib.Path(os.environ.get("LOOPD_BIN", REPO / "target/release/loopd"))
DATA = pathlib.Path(os.environ.get("LOOPD_SHARED_DATA", REPO.parent / "shared/data"))
ADMIN_KEY = "admin-key-for-the-python-client-tests-0123456789"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_certs(d: pathlib.Path) -> None:
    """A CA, and a server certificate for 127.0.0.1/localhost signed by it."""
    def run(*args):
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True)
    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
        "-subj", "/CN=loopd test CA")
    run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "server.key", "-out", "server.csr",
        "-subj", "/CN=localhost")
    (d / "san.ext").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n")
    run("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
        "-out", "server.pem", "-days", "2", "-extfile", "san.ext")


class Server:
    """One loopd process; `restart()` SIGKILLs it and starts it again on the same ports and data."""

    def __init__(self, root: pathlib.Path, extra: tuple = ()):
        self.root = root
        self.extra = list(extra)
        make_certs(root)
        (root / "admin.key").write_text(ADMIN_KEY)
        self.http_port, self.grpc_port = free_port(), free_port()
        self.proc = None
        self.ssl = ssl.create_default_context(cafile=str(root / "ca.pem"))
        self.start()

    @property
    def grpc(self) -> str:
        return f"127.0.0.1:{self.grpc_port}"

    @property
    def ca(self) -> pathlib.Path:
        return self.root / "ca.pem"

    def start(self, wait: bool = True) -> None:
        log = open(self.root / "server.log", "ab")
        self.proc = subprocess.Popen(
            [str(BIN), "serve", "--device", "cpu", "--data-dir", str(self.root / "data"),
             "--http-addr", f"127.0.0.1:{self.http_port}", "--grpc-addr", self.grpc,
             "--tls-cert", str(self.root / "server.pem"), "--tls-key", str(self.root / "server.key"),
             "--admin-key-file", str(self.root / "admin.key"), "--max-batch", "8", *self.extra],
            stdout=log, stderr=log)
        if wait:
            self.wait_ready()

    def wait_ready(self, timeout: float = 120) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"loopd exited ({self.proc.returncode}); see {self.root / 'server.log'}")
            try:
                urllib.request.urlopen(f"https://127.0.0.1:{self.http_port}/readyz", timeout=1, context=self.ssl)
                return
            except OSError:
                time.sleep(0.2)
        raise RuntimeError("loopd did not become ready")

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def restart(self) -> None:
        self.kill()
        self.start()

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.kill()

    def tenant(self, name: str, **limits) -> str:
        """A new tenant's key, through the admin HTTP route."""
        request = urllib.request.Request(
            f"https://127.0.0.1:{self.http_port}/v1/tenants", method="POST",
            data=json.dumps({"name": name, "limits": limits}).encode(),
            headers={"Authorization": f"Bearer {ADMIN_KEY}", "Content-Type": "application/json"})
        with urllib.request.urlopen(request, context=self.ssl) as r:
            return json.load(r)["key"]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    if not BIN.exists():
        pytest.fail(f"{BIN} is missing: cargo build --release --bin loopd first")
    s = Server(tmp_path_factory.mktemp("loopd"))
    yield s
    s.stop()


def corridor(part: str, count: int):
    files = sorted((DATA / "corridor" / part).glob("*.jpg"))[:count]
    assert len(files) == count, f"need {count} images in {DATA / 'corridor' / part}"
    return [f.read_bytes() for f in files]


def corridor_truth():
    """Query index -> the reference indices that show the same place (gt.csv)."""
    truth = {}
    for line in (DATA / "corridor/gt.csv").read_text().splitlines()[1:]:
        q, refs = line.split(",")
        truth[int(q)] = {int(r) for r in refs.split()}
    return truth


def euroc_stereo():
    """EuRoC's calibrated stereo camera from euroc-lcd/sensor{Left,Right}.yaml: the left camera
    (fx, fy, cx, cy, k1, k2, p1, p2, k3) and `create_session`'s `stereo` (the right camera's pose
    in the left's, its intrinsics and distortion)."""
    import re
    import numpy as np

    def sensor(side):
        text = (DATA / f"euroc-lcd/sensor{side}.yaml").read_text()
        grab = lambda key: [float(v) for v in re.search(key + r"\s*\[([^\]]*)\]", text, re.S).group(1).split(",")]  # noqa: E731
        return np.array(grab("data:")).reshape(4, 4), grab("intrinsics:"), grab("distortion_coefficients:") + [0.0]

    (tl, kl, dl), (tr, kr, dr) = sensor("Left"), sensor("Right")
    t = np.linalg.inv(tr) @ tl
    stereo = {"rotation": t[:3, :3].ravel().tolist(), "translation": t[:3, 3].tolist(),
              "right_intrinsics": kr, "right_distortion": dr}
    return kl + dl, stereo
