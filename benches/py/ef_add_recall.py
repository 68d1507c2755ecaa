"""Why the approximate index's recall@10 levels off below 0.99 (docs/performance.md, issue #33):
FAISS IndexHNSWFlat (M 16, inner product) on the real rows alone and on the real rows extended as
benches/ann.rs extends them (each synthetic row a real row mixed with another, weight 0.5-1, plus
Gaussian noise of norm 0.5, renormalised; numpy's generator, not the bench's, so the rows are
alike, not the same), at two expansions when adding (efConstruction) and three when searching.

usage: ef_add_recall.py CACHE.f32 N [EFC,...]
CACHE.f32: benches/ann.rs' cache of every image of ../shared/data (target/bench-cache/*.f32,
1,712-d rows); the first 512 values of each row are kept, renormalised (LOOPD_BENCH_ROW_DIMS=512).
Queries: 200 real rows, the row itself excluded; an answer scoring at least the exact 10th best counts.
"""
import sys
import time

import faiss
import numpy as np


def recall(index, X, qs, kth):
    D, I = index.search(X[qs], 11)
    r = []
    for i, q in enumerate(qs):
        got = [s for s, j in zip(D[i], I[i]) if j != q][:10]
        r.append(sum(s >= kth[i] - 1e-6 for s in got) / 10)
    return np.array(r)


def main():
    x = np.fromfile(sys.argv[1], dtype=np.float32).reshape(-1, 1712)[:, :512].copy()
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    n = int(sys.argv[2])
    efcs = [int(v) for v in (sys.argv[3] if len(sys.argv) > 3 else "64,200").split(",")]
    rng = np.random.default_rng(7)
    m = max(n - len(x), 0)
    a, b = rng.integers(0, len(x), m), rng.integers(0, len(x), m)
    w = (0.5 + 0.5 * rng.random(m, dtype=np.float32))[:, None]
    syn = w * x[a] + (1 - w) * x[b] + (0.5 / np.sqrt(512)) * rng.standard_normal((m, 512), dtype=np.float32)
    syn /= np.linalg.norm(syn, axis=1, keepdims=True)
    qs = rng.choice(len(x), 200, replace=False)
    for label, X in (("real rows alone", x), (f"{n} rows", np.vstack([x, syn]).astype(np.float32))):
        S = X[qs] @ X.T
        S[np.arange(len(qs)), qs] = -9
        kth = -np.partition(-S, 9, axis=1)[:, 9]
        for efc in efcs:
            index = faiss.IndexHNSWFlat(512, 16, faiss.METRIC_INNER_PRODUCT)
            index.hnsw.efConstruction = efc
            t = time.time()
            index.add(X)
            rate = len(X) / (time.time() - t)
            for ef in (64, 256, 1024):
                index.hnsw.efSearch = ef
                r = recall(index, X, qs, kth)
                print(f"{label}: efConstruction {efc} ({rate:.0f} rows/s), efSearch {ef}: "
                      f"recall@10 {r.mean():.4f}, queries below 1: {(r < 1).sum()}", flush=True)


if __name__ == "__main__":
    main()
