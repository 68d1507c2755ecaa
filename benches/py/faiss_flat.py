"""FAISS IndexFlatIP on the same random unit vectors as benches/search.rs (splitmix64 stream).

usage: faiss_flat.py N DIM SEED SINGLE_QUERIES BATCH [BATCHES]
prints one JSON line: build time, single-query and batch queries/s, top-1 ids of the first queries.
"""
import json
import sys
import time

import faiss
import numpy as np

GOLDEN = np.uint64(0x9E3779B97F4A7C15)
C1 = np.uint64(0xBF58476D1CE4E5B9)
C2 = np.uint64(0x94D049BB133111EB)


def unit_rows(seed, start, count, dim):
    """Rows start..start+count of the stream `seed`: uniform [-1, 1) values, rows normalised."""
    with np.errstate(over="ignore"):
        idx = np.arange(start * dim, (start + count) * dim, dtype=np.uint64)
        z = np.uint64(seed) + (idx + np.uint64(1)) * GOLDEN
        z = (z ^ (z >> np.uint64(30))) * C1
        z = (z ^ (z >> np.uint64(27))) * C2
        z = z ^ (z >> np.uint64(31))
    v = (z >> np.uint64(40)).astype(np.float32) * np.float32(2.0 / (1 << 24)) - np.float32(1.0)
    v = v.reshape(count, dim)
    v /= np.sqrt((v * v).sum(axis=1, dtype=np.float32))[:, None]
    return v


def main():
    n, dim, seed, singles, batch = (int(a) for a in sys.argv[1:6])
    batches = int(sys.argv[6]) if len(sys.argv) > 6 else 2
    t = time.perf_counter()
    index = faiss.IndexFlatIP(dim)
    step = max(1, (1 << 26) // dim)
    for s in range(0, n, step):
        index.add(unit_rows(seed, s, min(step, n - s), dim))
    build = time.perf_counter() - t
    q = unit_rows(seed + 1, 0, max(singles, batch), dim)
    index.search(q[:1], 10)  # warm-up
    t = time.perf_counter()
    top1 = []
    for i in range(singles):
        _, ids = index.search(q[i:i + 1], 10)
        top1.append(int(ids[0, 0]))
    single_qps = singles / (time.perf_counter() - t)
    t = time.perf_counter()
    for _ in range(batches):
        index.search(q[:batch], 10)
    batch_qps = batches * batch / (time.perf_counter() - t)
    print(json.dumps({"build_s": build, "single_qps": single_qps, "batch_qps": batch_qps, "top1": top1,
                      "threads": faiss.omp_get_max_threads()}))


if __name__ == "__main__":
    main()
