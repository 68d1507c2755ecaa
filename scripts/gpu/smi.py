"""Samples GPU memory used (MiB) and utilisation (%) every 0.25 s into a CSV of epoch seconds
(scripts/gpu-check; report.py reads it). Runs until killed."""
import subprocess
import sys
import time

with open(sys.argv[1], "w", buffering=1) as out:
    while True:
        t = time.time()
        try:
            r = subprocess.run(["nvidia-smi", "--query-gpu=memory.used,utilization.gpu", "--format=csv,noheader,nounits"],
                               capture_output=True, text=True, timeout=5)
            mem, util = r.stdout.strip().splitlines()[0].split(",")
            out.write(f"{t:.3f},{float(mem):.0f},{float(util):.0f}\n")
        except (OSError, ValueError, IndexError, subprocess.TimeoutExpired):
            pass
        time.sleep(max(0.0, 0.25 - (time.time() - t)))
