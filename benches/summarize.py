#!/usr/bin/env python3
"""Turns the output of `cargo bench --bench accel_build|accel_trace` (criterion) into a
markdown table: benchmark, median time, median throughput, and the ratio to a baseline row
of the same group (default: the Arbor row with the same thread suffix).

    cargo bench --features peers --bench accel_build | tee build.txt
    python3 benches/summarize.py build.txt
"""
import re
import sys

UNITS = {"ns": 1e-9, "µs": 1e-6, "us": 1e-6, "ms": 1e-3, "s": 1.0}


def parse(text):
    rows, name, extra, scene = [], None, {}, ""
    for line in text.splitlines():
        s = line.strip()
        m = re.match(r"^(\S+): \d+ triangles", s)
        if m:
            scene = m.group(1)
        m = re.match(r"^(build|trace)/\S+$", s)
        if m:
            name = s
            continue
        m = re.match(r"^time:\s+\[\S+ \S+ (\S+) (\S+) \S+ \S+\]", s)
        if m and name:
            rows.append({"name": name, "time": float(m.group(1)) * UNITS[m.group(2)]})
            continue
        m = re.match(r"^thrpt:\s+\[\S+ \S+ (\S+) (\S+)/s \S+ \S+\]", s)
        if m and rows and rows[-1]["name"] == name:
            v = float(m.group(1)) * {"elem": 1, "Kelem": 1e3, "Melem": 1e6, "Gelem": 1e9}[m.group(2)]
            rows[-1]["thrpt"] = v
        m = re.match(r"^(arbor|embree|obvhs) (\S+) (\d+)t: SAH ([\d.]+)", s)
        if m:
            extra[(scene, m.group(1), m.group(2).replace("-", "_"), m.group(3))] = float(m.group(4))
    return rows, extra


def main():
    rows, sah = parse(open(sys.argv[1], encoding="utf-8").read())
    build = any(r["name"].startswith("build") for r in rows)
    if build:
        print("| benchmark | median | throughput | SAH | time / Arbor FAST_TRACE | time / Arbor FAST_BUILD |")
        print("|---|---|---|---|---|---|")
    else:
        print("| benchmark | median | rays/s | time / Arbor |")
        print("|---|---|---|---|")
    for r in rows:
        parts = r["name"].split("/")
        group, who, variant, threads = "/".join(parts[:2]), parts[2], "/".join(parts[3:-1]), parts[-1]
        def ratio(base_name):
            base = next((b for b in rows if b["name"] == base_name), None)
            return f"{r['time'] / base['time']:.2f}×" if base else ""
        t = r["time"]
        ts = f"{t * 1e3:.1f} ms" if t < 10 else f"{t:.2f} s"
        th = r.get("thrpt")
        ths = f"{th / 1e6:.3f} M/s" if th else ""
        s = sah.get((parts[1], who, variant, threads.rstrip("t")))
        if build:
            rt, rb = ratio(f"{group}/arbor/fast_trace/{threads}"), ratio(f"{group}/arbor/fast_build/{threads}")
            print(f"| {r['name']} | {ts} | {ths} | {s if s is not None else ''} | {rt} | {rb} |")
        else:
            print(f"| {r['name']} | {ts} | {ths} | {ratio(f'{group}/arbor/{variant}/{threads}')} |")


if __name__ == "__main__":
    main()
