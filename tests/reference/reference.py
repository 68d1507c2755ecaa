"""Independent PyTorch implementation of loopd's descriptor network (docs/model.md).

Loads a loopd safetensors weight file (torchvision-style names, attention and fusion
included), runs the four ablation variants on preprocessed inputs, and compares with
descriptors computed by the Rust model.

usage: reference.py WEIGHTS INPUTS EXPECTED [--tol 1e-4]
  INPUTS:   safetensors with "inputs" [N, 3, H, W] (already normalised)
  EXPECTED: safetensors with one [N, 2048] tensor per variant name
Prints one line per variant and exits 1 if any differs by more than --tol.
"""
import argparse
import json
import sys

import torch
import torch.nn.functional as F
from safetensors import safe_open
from safetensors.torch import load_file

BN_EPS = 1e-5
BLOCKS = [3, 4, 6, 3]
KERNELS = [3, 5, 7]


def conv(w, x, prefix, stride=1, padding=0, groups=1):
    return F.conv2d(x, w[prefix + ".weight"], w.get(prefix + ".bias"), stride, padding, 1, groups)


def bn(w, x, prefix):
    return F.batch_norm(x, w[prefix + ".running_mean"], w[prefix + ".running_var"],
                        w[prefix + ".weight"], w[prefix + ".bias"], False, 0.0, BN_EPS)


def bottleneck(w, x, p, stride, v1):
    s1, s3 = (stride, 1) if v1 else (1, stride)
    y = F.relu(bn(w, conv(w, x, p + ".conv1", s1), p + ".bn1"))
    y = F.relu(bn(w, conv(w, y, p + ".conv2", s3, 1), p + ".bn2"))
    y = bn(w, conv(w, y, p + ".conv3"), p + ".bn3")
    if p + ".downsample.0.weight" in w:
        x = bn(w, conv(w, x, p + ".downsample.0", stride), p + ".downsample.1")
    return F.relu(y + x)


def gcm(w, x, p):
    c = x.shape[1]
    mx = F.max_pool2d(x, 2, 2, ceil_mode=True)
    av = F.avg_pool2d(x, 2, 2, ceil_mode=True)
    n, _, h, ww = mx.shape
    inter = torch.stack([mx, av], dim=2).reshape(n, 2 * c, h, ww)
    return conv(w, inter, p, padding=1, groups=c)


def channel_attention(w, x, p):
    c = x.shape[1]
    maps = []
    for k in KERNELS:
        b = f"{p}.branch{k}"
        y = conv(w, x, b + ".conv", padding=k // 2, groups=c)
        y = gcm(w, gcm(w, y, b + ".gcm1"), b + ".gcm2")
        maps.append(torch.sigmoid(y.mean(dim=(2, 3))))
    h = F.relu(F.linear(torch.cat(maps, 1), w[p + ".fc1.weight"], w[p + ".fc1.bias"]))
    weights = 2 * torch.sigmoid(F.linear(h, w[p + ".fc2.weight"], w[p + ".fc2.bias"]))
    return x * weights[:, :, None, None]


def spatial_attention(w, u, p):
    m = torch.cat([u.amax(1, keepdim=True), u.mean(1, keepdim=True)], 1)
    m = conv(w, conv(w, m, p + ".conv1", padding=1), p + ".conv2")
    return u * (2 * torch.sigmoid(m))


def descriptor(w, x, attention, fusion, v1):
    y = F.relu(bn(w, conv(w, x, "conv1", 2, 3), "bn1"))
    y = F.max_pool2d(y, 3, 2, 1)
    shallow = None
    for s, n in enumerate(BLOCKS):
        for b in range(n):
            y = bottleneck(w, y, f"layer{s + 1}.{b}", (1 if s == 0 else 2) if b == 0 else 1, v1)
        if attention:
            y = channel_attention(w, y, f"attention.{s}.channel")
            y = spatial_attention(w, y, f"attention.{s}.spatial")
        if s == 0:
            shallow = y
    if fusion:
        pooled = F.adaptive_max_pool2d(shallow, y.shape[2:])
        y = y + conv(w, pooled, "fusion.conv")
    return F.normalize(y.mean(dim=(2, 3)), dim=1)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("weights")
    ap.add_argument("inputs")
    ap.add_argument("expected")
    ap.add_argument("--tol", type=float, default=1e-4)
    a = ap.parse_args()
    torch.set_grad_enabled(False)
    w = {k: t.float() for k, t in load_file(a.weights).items()}
    with safe_open(a.weights, "pt") as f:
        meta = f.metadata() or {}
    v1 = meta.get("stride_layout", "v1") == "v1"
    x = load_file(a.inputs)["inputs"].float()
    expected = load_file(a.expected)
    worst = 0.0
    report = {}
    for name, att, fus in [("attention+fusion", True, True), ("attention", True, False),
                           ("fusion", False, True), ("backbone", False, False)]:
        d = descriptor(w, x, att, fus, v1)
        diff = (d - expected[name].float()).abs().max().item()
        report[name] = diff
        worst = max(worst, diff)
    print(json.dumps({"max_abs_diff": report, "tol": a.tol}))
    sys.exit(0 if worst <= a.tol else 1)


if __name__ == "__main__":
    main()
