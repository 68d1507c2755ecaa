"""FAISS IndexHNSWFlat beside loopd's approximate index (benches/ann.rs), on the same rows.

usage: faiss_hnsw.py ROWS_F32 QUERIES_TXT DIM [M [EF_CONSTRUCTION]]
ROWS_F32: the unit rows, row-major little-endian f32; QUERIES_TXT: one row number per line,
each queried as a stored frame (itself left out). M (default 16) and efConstruction (default
128) as loopd's graph is built (benches/ann.rs passes its own), inner product. Prints one JSON
line: build rate, and for each efSearch its recall@10 against exact search (IndexFlatIP; a result scoring at least the 10th exact score counts, so exact ties
count either way) and its median single-query time.
"""
import json
import sys
import time

import faiss
import numpy as np

# Scores this close to the 10th best count as ties (benches/ann.rs uses the same).
TIE = 1e-6


def main():
    rows_path, queries_path, dim = sys.argv[1], sys.argv[2], int(sys.argv[3])
    m = int(sys.argv[4]) if len(sys.argv) > 4 else 16
    ef_construction = int(sys.argv[5]) if len(sys.argv) > 5 else 128
    x = np.fromfile(rows_path, dtype=np.float32).reshape(-1, dim)
    queries = [int(line) for line in open(queries_path) if line.strip()]
    flat = faiss.IndexFlatIP(dim)
    flat.add(x)
    gs, gt = flat.search(x[queries], 11)
    # The 10th best score of each query (itself left out): a result scoring as well counts as
    # found, so that exact ties (duplicate rows) count whichever of them is returned.
    kth = [[s for s, i in zip(gs[j], gt[j]) if i != q and i >= 0][9] for j, q in enumerate(queries)]
    index = faiss.IndexHNSWFlat(dim, m, faiss.METRIC_INNER_PRODUCT)
    index.hnsw.efConstruction = ef_construction
    t = time.perf_counter()
    index.add(x)
    build = len(x) / (time.perf_counter() - t)
    sweep = []
    for ef in (16, 32, 64, 128, 256, 512, 1024):
        index.hnsw.efSearch = ef
        times, found = [], 0
        for i, q in enumerate(queries):
            t = time.perf_counter()
            scores, ids = index.search(x[q:q + 1], 11)
            times.append((time.perf_counter() - t) * 1e3)
            got = [s for s, j in zip(scores[0], ids[0]) if j != q and j >= 0][:10]
            found += sum(s >= kth[i] - TIE for s in got)
        sweep.append({"ef": ef, "recall10": found / (10 * len(queries)), "p50_ms": float(np.median(times))})
    print(json.dumps({"build_per_s": build, "m": m, "ef_construction": ef_construction, "threads": faiss.omp_get_max_threads(), "sweep": sweep}))


if __name__ == "__main__":
    main()
