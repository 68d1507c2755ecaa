"""How many reduced-dimension candidates hold the full descriptor's top k (docs/storage.md).

usage: reduction_recall.py CACHE.f32 [CACHE.f32 ...]
CACHE.f32: `loopd eval --cache-dir DIR` descriptor files (row-major f32, 1,712-d for the shipped
model). Rows of all files together; each row queries the others. Prints, for k in (1, 5, 10, 20),
dimensions D and candidate counts C, the share of the full top k within the first D values' top C.
"""
import sys

import numpy as np


def main():
    x = np.concatenate([np.fromfile(f, dtype=np.float32).reshape(-1, 1712) for f in sys.argv[1:]])
    s = x @ x.T
    np.fill_diagonal(s, -9)
    for k in (1, 5, 10, 20):
        exact = np.argsort(-s, axis=1)[:, :k]
        for d in (128, 256, 384, 512, 768):
            r = x[:, :d] / np.linalg.norm(x[:, :d], axis=1, keepdims=True)
            sr = r @ r.T
            np.fill_diagonal(sr, -9)
            order = np.argsort(-sr, axis=1)
            out = []
            for c in (k + 16, 2 * k + 16, 4 * k + 32, 8 * k + 64, 16 * k + 64):
                cand = order[:, :c]
                top = np.take_along_axis(cand, np.argsort(-np.take_along_axis(s, cand, 1), axis=1)[:, :k], 1)
                share = np.mean([len(set(top[i]) & set(exact[i])) / k for i in range(len(x))])
                out.append(f"C={c}:{share:.4f}")
            print(f"{len(x)} rows k={k} D={d}", " ".join(out))


if __name__ == "__main__":
    main()
