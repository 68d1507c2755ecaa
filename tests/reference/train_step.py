"""PyTorch reference of one `loopd train` step (docs/training.md).

Rebuilds the descriptor with reference.py's independent layers, the multi-similarity loss with
its mining, global gradient-norm clipping and one AdamW step, and compares with what the Rust
trainer wrote.

usage: train_step.py WEIGHTS BATCH EXPECTED [--tol-loss 1e-5] [--tol-grad 1e-4]
  WEIGHTS:  full loopd weight file (heads included) before the step
  BATCH:    "inputs" [N,3,H,W] (normalised), "pos", "neg" [N,N] masks, "hyper" =
            [lr, weight_decay, clip_norm, alpha, beta, lambda, epsilon]
  EXPECTED: "loss" [1], "grad.<name>" (clipped) and "after.<name>" for every trained tensor
Prints a JSON summary; exits 1 if any difference exceeds its tolerance.
"""
import argparse
import json
import os
import sys

import torch
from safetensors import safe_open
from safetensors.torch import load_file

sys.path.insert(0, os.path.dirname(__file__))
from reference import descriptor  # noqa: E402


def multi_similarity(d, pos, neg, alpha, beta, lam, eps):
    s = d @ d.t()
    with torch.no_grad():
        big = 1e4
        min_pos = (s + (1 - pos) * big).amin(1, keepdim=True)
        max_neg = (s - (1 - neg) * big).amax(1, keepdim=True)
        pos_keep = pos * (s - eps < max_neg).float()
        neg_keep = neg * (s + eps > min_pos).float()
    pos_term = (pos_keep * torch.exp(-alpha * (s - lam))).sum(1)
    neg_term = (neg_keep * torch.exp(beta * (s - lam))).sum(1)
    return (torch.log1p(pos_term) / alpha + torch.log1p(neg_term) / beta).mean()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("weights")
    ap.add_argument("batch")
    ap.add_argument("expected")
    ap.add_argument("--tol-loss", type=float, default=1e-5)
    ap.add_argument("--tol-grad", type=float, default=1e-4)
    a = ap.parse_args()
    w = {k: t.float() for k, t in load_file(a.weights).items()}
    with safe_open(a.weights, "pt") as f:
        v1 = (f.metadata() or {}).get("stride_layout", "v1") == "v1"
    b = load_file(a.batch)
    exp = load_file(a.expected)
    lr, wd, clip, alpha, beta, lam, eps = b["hyper"].double().tolist()
    trained = sorted(k[len("grad."):] for k in exp if k.startswith("grad."))
    params = []
    for k in trained:
        w[k] = w[k].clone().requires_grad_(True)
        params.append(w[k])
    d = descriptor(w, b["inputs"].float(), True, True, v1)
    loss = multi_similarity(d, b["pos"].float(), b["neg"].float(), alpha, beta, lam, eps)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(params, clip)
    grads = {k: w[k].grad.detach().clone() for k in trained}
    opt = torch.optim.AdamW(params, lr=lr, betas=(0.9, 0.999), eps=1e-8, weight_decay=wd)
    opt.step()
    loss_diff = abs(loss.item() - exp["loss"].item())
    # Relative to the largest gradient of the step: tiny entries carry float noise only.
    scale = max(g.abs().max().item() for g in grads.values())
    grad_diff = max((grads[k] - exp["grad." + k]).abs().max().item() for k in trained) / scale
    # Adam's first step moves each parameter by about lr * sign(grad): compared where the gradient
    # is well above float noise (elsewhere the sign itself is noise).
    param_diff = max(((w[k].detach() - exp["after." + k]).abs() * (grads[k].abs() > 1e-4 * scale)).max().item()
                     for k in trained)
    report = {"loss": loss.item(), "loss_diff": loss_diff, "grad_rel_diff": grad_diff,
              "param_diff_after_adamw": param_diff, "tensors": len(trained), "max_grad": scale}
    print(json.dumps(report))
    ok = loss_diff <= a.tol_loss and grad_diff <= a.tol_grad and param_diff <= 1e-6 + 1e-2 * lr
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
