"""Turns scripts/gpu-check's rows into one Markdown table file and one JSON file.

usage: report.py DIR OUT_MD OUT_JSON [--check]
  DIR holds rows-*.jsonl (benches/gpu.rs and peer.py), search.md (benches/search.rs's tables),
  smi.csv (epoch seconds, GPU memory used MiB, utilisation %, sampled by smi.py; absent on a CPU)
  and meta.json. Each row gets the peak GPU memory and mean utilisation sampled over its t0..t1.
  --check: exits 1 unless every section has its rows with numbers in them (the dry run in CI).
"""
import glob
import json
import os
import sys


def load_rows(d):
    rows = []
    for path in sorted(glob.glob(os.path.join(d, "rows-*.jsonl"))):
        with open(path) as f:
            rows += [json.loads(line) for line in f if line.startswith("{")]
    return rows


def load_smi(d):
    path = os.path.join(d, "smi.csv")
    if not os.path.exists(path):
        return []
    out = []
    with open(path) as f:
        for line in f:
            try:
                t, mem, util = (float(v) for v in line.split(","))
                out.append((t, mem, util))
            except ValueError:
                continue
    return out


def markdown_tables(path):
    """Every Markdown table of a file as a list of dicts (header -> cell)."""
    if not os.path.exists(path):
        return [], ""
    text = open(path).read()
    tables, header = [], None
    for line in text.splitlines():
        if not line.startswith("|"):
            header = None
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if header is None:
            header = cells
            tables.append([])
        elif set("".join(cells)) <= set("-: "):
            continue
        else:
            tables[-1].append(dict(zip(header, cells)))
    return tables, text


def fmt(v, digits=1):
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def main():
    d, out_md, out_json = sys.argv[1:4]
    check = "--check" in sys.argv
    rows = load_rows(d)
    smi = load_smi(d)
    meta = json.load(open(os.path.join(d, "meta.json"))) if os.path.exists(os.path.join(d, "meta.json")) else {}
    for r in rows:
        if "t0" in r and smi:
            window = [s for s in smi if r["t0"] - 0.3 <= s[0] <= r["t1"] + 0.3]
            if window:
                r["gpu_mem_mib"] = max(s[1] for s in window)
                r["gpu_util_pct"] = sum(s[2] for s in window) / len(window)
    search_tables, search_text = markdown_tables(os.path.join(d, "search.md"))
    fwd = [r for r in rows if r["section"] == "forward"]
    diff = [r for r in rows if r["section"] == "diff"]
    eng = [r for r in rows if r["section"] == "engine"]
    trn = [r for r in rows if r["section"] == "train"]
    skipped = [r for r in rows if r["section"] == "compile_skipped"]

    md = [f"# scripts/gpu-check — {meta.get('date', '?')}", "",
          f"GPU: {meta.get('gpu', 'none (CPU dry run)')}; driver {meta.get('driver', '-')}; "
          f"torch {meta.get('torch', '-')}; CUDA {meta.get('cuda', '-')}; host CPUs {meta.get('cpus', '-')}", "",
          "GPU memory: the largest `memory.used` nvidia-smi sampled (every 0.25 s) during the row, the "
          "CUDA context and the caching allocator's reserve included; PyTorch rows also give "
          "`torch.cuda.max_memory_allocated`. Utilisation: mean of the samples.", "",
          "## Forward pass (random weights, 2048-d descriptors copied back to the host)", "",
          "| dtype | batch | variant | loopd img/s | loopd p50 ms | PyTorch eager img/s | eager p50 ms | loopd / eager | "
          "torch.compile img/s | loopd GPU MiB | eager GPU MiB (allocated) | loopd util % |",
          "|--|--:|--|--:|--:|--:|--:|--:|--:|--:|--:|--:|"]
    key = lambda r: (r["dtype"], r["batch"], r["variant"])
    peer = {key(r): r for r in fwd if r["impl"] == "pytorch-eager"}
    comp = {key(r): r for r in fwd if r["impl"] == "pytorch-compile"}
    for r in [r for r in fwd if r["impl"] == "loopd"]:
        p, c = peer.get(key(r), {}), comp.get(key(r), {})
        ratio = r["img_s"] / p["img_s"] if p.get("img_s") else None
        md.append(f"| {r['dtype']} | {r['batch']} | {r['variant']} | {fmt(r['img_s'])} | {fmt(r['p50_ms'], 2)} | "
                  f"{fmt(p.get('img_s'))} | {fmt(p.get('p50_ms'), 2)} | {fmt(ratio, 2)} | {fmt(c.get('img_s'))} | "
                  f"{fmt(r.get('gpu_mem_mib'), 0)} | {fmt(p.get('gpu_mem_mib'), 0)} ({fmt(p.get('torch_peak_alloc_mib'), 0)}) | "
                  f"{fmt(r.get('gpu_util_pct'), 0)} |")
    for r in comp.values():
        md.append(f"\ntorch.compile {r['dtype']} batch {r['batch']}: compiled in {r['compile_s']:.0f} s.")
    for r in skipped:
        md.append(f"\ntorch.compile {r['dtype']} batch {r['batch']} skipped: {r['reason']}.")
    md += ["", "## Descriptors: loopd against the PyTorch reference on the same weights and inputs", "",
           "| dtype | variant | max abs diff (same dtype) | loopd vs PyTorch f32 |", "|--|--|--:|--:|"]
    for r in diff:
        md.append(f"| {r['dtype']} | {r['variant']} | {r['max_abs_diff']:.2e} | {r['loopd_vs_pytorch_f32']:.2e} |")
    md += ["", "## Engine: concurrent clients, JPEG in (decoded on the CPU workers), full network", "",
           "| batch buckets | clients | dtype | max_batch | img/s | p50 ms | p99 ms | mean batch | largest batch (bucket) | GPU util % | GPU MiB |",
           "|--|--:|--|--:|--:|--:|--:|--:|--:|--:|--:|"]
    for r in eng:
        md.append(f"| {r.get('batch_buckets', '-')} | {r['clients']} | {r['dtype']} | {r['max_batch']} | {fmt(r['img_s'])} | {fmt(r['p50_ms'])} | "
                  f"{fmt(r['p99_ms'])} | {fmt(r['mean_batch'])} | {fmt(r['largest_batch_bucket'], 0)} | "
                  f"{fmt(r.get('gpu_util_pct'), 0)} | {fmt(r.get('gpu_mem_mib'), 0)} |")
    md += ["", "## Training step (heads trained, backbone frozen, multi-similarity loss, AdamW)", "",
           "| autocast | batch | img/s | step p50 ms | GPU MiB | GPU util % |", "|--|--:|--:|--:|--:|--:|"]
    for r in trn:
        md.append(f"| {r['autocast']} | {r['batch']} | {fmt(r['img_s'])} | {fmt(r['step_ms'])} | "
                  f"{fmt(r.get('gpu_mem_mib'), 0)} | {fmt(r.get('gpu_util_pct'), 0)} |")
    md += ["", "## Search (benches/search.rs: exact top-10, random unit vectors)", "", search_text.strip(), ""]
    with open(out_md, "w") as f:
        f.write("\n".join(md) + "\n")
    with open(out_json, "w") as f:
        json.dump({"meta": meta, "rows": rows, "search": search_tables}, f, indent=1)
    print("\n".join(md))

    if check:
        problems = []
        impls = {r["impl"] for r in fwd}
        for need in ["loopd", "pytorch-eager"]:
            if need not in impls:
                problems.append(f"no forward rows of {need}")
        if len([r for r in fwd if r["impl"] == "loopd"]) != len(peer):
            problems.append("loopd and PyTorch forward rows differ in number")
        for name, part in [("diff", diff), ("engine", eng), ("train", trn)]:
            if not part:
                problems.append(f"no {name} rows")
        for r in fwd + eng + trn:
            if not (isinstance(r.get("img_s"), float) and r["img_s"] > 0):
                problems.append(f"row without a rate: {r}")
        for r in diff:
            if not r["max_abs_diff"] < 1e-3:
                problems.append(f"descriptors differ from the PyTorch reference: {r}")
        if not search_tables or not search_tables[0]:
            problems.append("no search table")
        if problems:
            print("gpu-check outputs are incomplete:\n  " + "\n  ".join(problems), file=sys.stderr)
            sys.exit(1)
        print(f"gpu-check outputs: {len(rows)} rows, {sum(map(len, search_tables))} search rows, all present",
              file=sys.stderr)


if __name__ == "__main__":
    main()
