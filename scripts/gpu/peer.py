"""PyTorch peer of benches/gpu.rs's forward section (scripts/gpu-check).

The same network (tests/reference/reference.py, an independent PyTorch implementation), the same
random weights and inputs that `gpu forward` wrote into WORK: timed in eager mode (channels-last,
as loopd runs) at the same precisions, batches and variants, then with torch.compile where time
allows, and the largest difference between its descriptors and loopd's in each precision.
Prints one JSON object per row, as `gpu forward` does.

usage: peer.py WORK   env: GPU_DEVICE, GPU_DTYPES, GPU_BATCHES, GPU_SECONDS, GPU_SIDE,
                           PEER_COMPILE (e.g. "f16:32,f16:128"; empty: none), PEER_COMPILE_UNTIL
                           (seconds since the start after which no compile is begun, default 120)
"""
import json
import os
import sys
import time

import torch
from safetensors.torch import load_file

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from reference import descriptor  # noqa: E402

KINDS = {"f32": torch.float32, "f16": torch.float16, "bf16": torch.bfloat16}
VARIANTS = {"attention+fusion": (True, True), "backbone": (False, False)}
started = time.time()


def env(name, default):
    return os.environ.get(name, default)


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(device, items, budget, f):
    f()
    f()
    sync(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    t0 = time.time()
    start = time.perf_counter()
    lat = []
    while len(lat) < 5 or (time.perf_counter() - start < budget and len(lat) < 2000):
        t = time.perf_counter()
        f()
        sync(device)
        lat.append((time.perf_counter() - t) * 1e3)
    rate = items * len(lat) / (time.perf_counter() - start)
    lat.sort()
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else None
    return rate, lat[round((len(lat) - 1) * 0.5)], len(lat), t0, time.time(), peak


def main():
    work = sys.argv[1]
    torch.set_grad_enabled(False)
    device = torch.device(env("GPU_DEVICE", "cuda"))
    dtypes = env("GPU_DTYPES", "f32,f16,bf16").split(",")
    batches = [int(b) for b in env("GPU_BATCHES", "1,8,32,128").split(",")]
    budget = float(env("GPU_SECONDS", "1.5"))
    side = int(env("GPU_SIDE", "224"))
    w32 = load_file(os.path.join(work, "weights.safetensors"))
    check = load_file(os.path.join(work, "inputs.safetensors"))["inputs"]

    def run(w, x, variant, kind):
        att, fus = VARIANTS[variant]
        x = x.to(device, kind, non_blocking=False).contiguous(memory_format=torch.channels_last)
        return descriptor(w, x, att, fus, True).float().cpu()

    for name in dtypes:
        kind = KINDS[name]
        w = {k: t.to(device, kind if t.is_floating_point() else t.dtype) for k, t in w32.items()}
        theirs = load_file(os.path.join(work, f"loopd-{name}.safetensors"))
        w_ref = {k: t.to(device, torch.float32) for k, t in w32.items()}
        for variant in VARIANTS:
            ours = torch.nn.functional.normalize(run(w, check, variant, kind), dim=1)
            ref32 = run(w_ref, check, variant, torch.float32)
            print(json.dumps({"section": "diff", "dtype": name, "variant": variant,
                              "max_abs_diff": (ours - theirs[variant]).abs().max().item(),
                              "loopd_vs_pytorch_f32": (theirs[variant] - ref32).abs().max().item()}), flush=True)
        for b in batches:
            x = torch.randn(b, 3, side, side)
            for variant in ["backbone", "attention+fusion"]:
                print(f"peer eager {name} batch {b} {variant}", file=sys.stderr, flush=True)
                rate, p50, calls, t0, t1, peak = timed(device, b, budget, lambda: run(w, x, variant, kind))
                print(json.dumps({"section": "forward", "impl": "pytorch-eager", "dtype": name, "batch": b,
                                  "variant": variant, "img_s": rate, "p50_ms": p50, "calls": calls,
                                  "t0": t0, "t1": t1, "torch_peak_alloc_mib": peak}), flush=True)
        del w
    until = float(env("PEER_COMPILE_UNTIL", "120"))
    for cell in filter(None, env("PEER_COMPILE", "").split(",")):
        name, b = cell.split(":")
        b = int(b)
        if time.time() - started > until:
            print(json.dumps({"section": "compile_skipped", "dtype": name, "batch": b,
                              "reason": f"past {until:.0f} s of the peer's time"}), flush=True)
            continue
        kind = KINDS[name]
        w = {k: t.to(device, kind if t.is_floating_point() else t.dtype) for k, t in w32.items()}
        net = torch.compile(lambda x: descriptor(w, x, True, True, True))
        x = torch.randn(b, 3, side, side)

        def call():
            y = x.to(device, kind).contiguous(memory_format=torch.channels_last)
            return net(y).float().cpu()

        print(f"peer compile {name} batch {b}", file=sys.stderr, flush=True)
        c0 = time.perf_counter()
        call()
        compile_s = time.perf_counter() - c0
        rate, p50, calls, t0, t1, peak = timed(device, b, budget, call)
        print(json.dumps({"section": "forward", "impl": "pytorch-compile", "dtype": name, "batch": b,
                          "variant": "attention+fusion", "img_s": rate, "p50_ms": p50, "calls": calls,
                          "t0": t0, "t1": t1, "torch_peak_alloc_mib": peak, "compile_s": compile_s}), flush=True)


if __name__ == "__main__":
    main()
