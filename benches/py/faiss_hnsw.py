"""FAISS IndexHNSWFlat beside loopd's approximate index (benches/ann.rs), on the same rows.

usage: faiss_hnsw.py ROWS_F32 QUERIES_TXT DIM
ROWS_F32: the unit rows, row-major little-endian f32; QUERIES_TXT: one row number per line,
each queried as a stored frame (itself left out). M 16, efConstruction 64 (loopd's settings),
inner product. Prints one JSON line: build rate, and for each efSearch its recall@10 against
exact search (IndexFlatIP) and its median single-query time.
"""
import json
import sys
import time

import faiss
import numpy as np


def without_self(ids, q, k):
    return [int(i) for i in ids if i != q and i >= 0][:k]


def main():
    rows_path, queries_path, dim = sys.argv[1], sys.argv[2], int(sys.argv[3])
    x = np.fromfile(rows_path, dtype=np.float32).reshape(-1, dim)
    queries = [int(line) for line in open(queries_path) if line.strip()]
    flat = faiss.IndexFlatIP(dim)
    flat.add(x)
    _, gt = flat.search(x[queries], 11)
    truth = [without_self(gt[i], q, 10) for i, q in enumerate(queries)]
    index = faiss.IndexHNSWFlat(dim, 16, faiss.METRIC_INNER_PRODUCT)
    index.hnsw.efConstruction = 64
    t = time.perf_counter()
    index.add(x)
    build = len(x) / (time.perf_counter() - t)
    sweep = []
    for ef in (16, 32, 64, 128, 256, 512, 1024):
        index.hnsw.efSearch = ef
        times, found = [], 0
        for i, q in enumerate(queries):
            t = time.perf_counter()
            _, ids = index.search(x[q:q + 1], 11)
            times.append((time.perf_counter() - t) * 1e3)
            found += len(set(without_self(ids[0], q, 10)) & set(truth[i]))
        sweep.append({"ef": ef, "recall10": found / (10 * len(queries)), "p50_ms": float(np.median(times))})
    print(json.dumps({"build_per_s": build, "threads": faiss.omp_get_max_threads(), "sweep": sweep}))


if __name__ == "__main__":
    main()
