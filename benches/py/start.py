"""A server's start and its first requests: `loopd serve --device cpu` started from nothing (an empty
data folder), the time until /readyz answers, then single images and bursts of 32 images to
/v1/embed (32 requests at once, real Corridor frames), the first ones and again, and the CPU time
the server used. Binaries alternate, so that a drift of the machine falls on all of them alike.

usage: start.py ROUNDS BINARY [BINARY ...]   (from the repository root, libtorch on LD_LIBRARY_PATH)
prints a Markdown table: one row per binary, medians over the rounds.
"""
import concurrent.futures as cf
import glob
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request

DATA = os.environ.get("LOOPD_SHARED_DATA", "../shared/data")
FILES = sorted(glob.glob(f"{DATA}/corridor/ref/*.jpg"))[:66]
if len(FILES) < 66:
    sys.exit(f"start.py: the Corridor's frames are not under {DATA}/corridor/ref")
IMAGES = [open(p, "rb").read() for p in FILES]
STEPS = [("first image", 1, 0), ("first 32", 32, 1), ("next image", 1, 33), ("next 32", 32, 34)]


def port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def one(binary):
    http, grpc = port(), port()
    with tempfile.TemporaryDirectory() as d:
        t0 = time.monotonic()
        p = subprocess.Popen([binary, "serve", "--device", "cpu", "--data-dir", f"{d}/data",
                              "--http-addr", f"127.0.0.1:{http}", "--grpc-addr", f"127.0.0.1:{grpc}"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            while True:
                if p.poll() is not None:
                    sys.exit(f"start.py: {binary} exited with {p.returncode}")
                try:
                    urllib.request.urlopen(f"http://127.0.0.1:{http}/readyz", timeout=1)
                    break
                except OSError:
                    time.sleep(0.02)
            row = {"ready s": time.monotonic() - t0}

            def embed(body):
                r = urllib.request.Request(f"http://127.0.0.1:{http}/v1/embed", data=body, method="POST")
                return urllib.request.urlopen(r, timeout=120).read()

            for name, n, off in STEPS:
                t = time.monotonic()
                with cf.ThreadPoolExecutor(n) as ex:
                    list(ex.map(embed, IMAGES[off:off + n]))
                row[f"{name} s"] = time.monotonic() - t
            with open(f"/proc/{p.pid}/stat") as f:
                fields = f.read().rsplit(") ", 1)[1].split()
            row["server CPU-s"] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        finally:
            p.terminate()
            p.wait()
    return row


def main():
    rounds, binaries = int(sys.argv[1]), sys.argv[2:]
    rows = {b: [] for b in binaries}
    for _ in range(rounds):
        for b in binaries:
            rows[b].append(one(b))
    cols = list(rows[binaries[0]][0])
    print("| binary | " + " | ".join(cols) + " |")
    print("|---|" + "--:|" * len(cols))
    for b in binaries:
        med = [statistics.median(r[c] for r in rows[b]) for c in cols]
        print(f"| {b} | " + " | ".join(f"{m:.2f}" for m in med) + " |")


if __name__ == "__main__":
    main()
