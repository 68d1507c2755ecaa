"""Sequence scores over the full similarity matrix, against what the server computes on its
candidates (docs/verification.md): Nordland-style aligned traversals, ±2 places.

    loopd eval --sequence S --query-sequence W --gt aligned --range R --cache-dir C ...
    .venv/bin/python scripts/sequence-matrix.py C/REF.f32 C/QUERY.f32 N

REF.f32 and QUERY.f32 are loopd eval's descriptor caches of the two traversals (the reference is
written first), N the frames of each. Prints R@100P and recall@1 for the descriptor alone, rows
z-scored over the whole map and a causal or centred window of L frames (margin over the best
reference more than 10 frames away), then the same on the server's candidates (its 20 best
matches and the past's votes) with statistics over every reference, over 256 of them (what the
server does) and across the candidates (the earlier rule), and the wrong first answers at L 10,
20 and 40."""
import sys
import numpy as np

ref = np.fromfile(sys.argv[1], dtype=np.float32)
qry = np.fromfile(sys.argv[2], dtype=np.float32)
n = int(sys.argv[3])
ref, qry = ref.reshape(n, -1), qry.reshape(n, -1)
TOL, WINDOW = 2, 10
S = qry @ ref.T


def r100(best, score):
    tp, r = 0, 0.0
    for q in np.argsort(-score, kind="stable"):
        if abs(best[q] - q) > TOL:
            break
        tp += 1
        r = tp / len(best)
    return r, np.mean(np.abs(best - np.arange(len(best))) <= TOL)


def margins(M):
    best = M.argmax(1)
    out = np.zeros(len(best))
    for q, b in enumerate(best):
        m = M[q].copy()
        top = m[b]
        m[max(0, b - WINDOW):b + WINDOW + 1] = -np.inf
        out[q] = top - m.max()
    return best, out


print("descriptor only      R@100P %.3f recall@1 %.3f" % r100(S.argmax(1), S.max(1)))
Z = (S - S.mean(1, keepdims=True)) / S.std(1, keepdims=True)
for L in (10, 20, 40):
    for centred in (False, True):
        K, C = np.zeros_like(Z), np.zeros_like(Z)
        for j in (range(-(L // 2), L - L // 2) if centred else range(L)):
            qi, ri = np.arange(n) - j, np.arange(n) - j
            mask = ((qi >= 0) & (qi < n))[:, None] & ((ri >= 0) & (ri < n))[None, :]
            K += np.where(mask, Z[np.clip(qi, 0, n - 1)][:, np.clip(ri, 0, n - 1)], 0)
            C += mask
        best, marg = margins(K / np.maximum(C, 1))
        r, r1 = r100(best, marg)
        wrong = np.where(np.abs(best - np.arange(n)) > TOL)[0]
        kind = "centred" if centred else "causal "
        print(f"L {L:3d} {kind} matrix     R@100P {r:.3f} recall@1 {r1:.3f}"
              + ("" if centred else f"  wrong first answers at {wrong.tolist()}"))

sample = np.arange(0, n, max(1, -(-n // 256)))
top5 = np.argsort(-S, 1)[:, :5]
for L in (10, 20, 40):
    for stats in ("all", "256", "candidates"):
        best, marg = np.zeros(n, int), np.zeros(n)
        for q in range(n):
            cands = set(np.argsort(-S[q])[:20].tolist())
            for j in range(1, min(L, q + 1)):
                cands.update(int(v + j) for v in top5[q - j] if v + j < n)
            cands = sorted(cands)
            hist = [q - j for j in range(L) if q - j >= 0]
            scores = []
            for c in cands:
                z = []
                for j, h in enumerate(hist):
                    if c - j < 0:
                        break
                    if stats == "all":
                        mu, sd = S[h].mean(), S[h].std()
                    elif stats == "256":
                        mu, sd = S[h, sample].mean(), S[h, sample].std()
                    else:
                        v = np.array([S[h, cc - j] for cc in cands if cc - j >= 0])
                        mu, sd = v.mean(), max(v.std(), 1e-6)
                    z.append((S[h, c - j] - mu) / sd)
                scores.append(np.mean(z) if z else -np.inf)
            scores = np.array(scores)
            i = int(np.argmax(scores))
            others = [scores[k] for k, c in enumerate(cands) if abs(c - cands[i]) > WINDOW]
            best[q], marg[q] = cands[i], scores[i] - (max(others) if others else scores.min())
        print(f"L {L:3d} candidates, statistics over {stats:10s} R@100P %.3f recall@1 %.3f" % r100(best, marg))
