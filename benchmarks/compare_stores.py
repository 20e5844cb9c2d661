"""Compare two data roots array by array: every Zarr store, every array (values bit for bit, dtype,
shape, chunks, attrs) and every other file (bytes), as a refactoring's "same stores" check.

    python -m benchmarks.compare_stores BEFORE_ROOT AFTER_ROOT [--ignore-attr NAME ...]

Prints one line per difference (values changed, attrs changed or removed) and, apart, what the
second root adds (new stores, arrays, attrs). Exit status 1 when anything differs.
Provenance attrs that change with every commit (``code_version``, ``package_versions``) are ignored.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import zarr

ALWAYS_IGNORED = {"code_version", "package_versions"}


def _dump(v) -> str:
    return json.dumps(v, sort_keys=True, default=str)


class Comparison:
    def __init__(self, ignore: set[str]):
        self.ignore, self.diffs, self.additions, self.arrays = ignore, [], [], 0

    def attrs(self, a: dict, b: dict, where: str) -> None:
        a = {k: v for k, v in a.items() if k not in self.ignore}
        b = {k: v for k, v in b.items() if k not in self.ignore}
        changed = sorted(k for k in set(a) & set(b) if _dump(a[k]) != _dump(b[k]))
        removed = sorted(set(a) - set(b))
        if changed or removed:
            self.diffs.append(f"{where}: attrs changed {changed} removed {removed}")
        if set(b) - set(a):
            self.additions.append(f"{where}: attrs added {sorted(set(b) - set(a))}")

    def group(self, ga, gb, where: str) -> None:
        self.attrs(ga.attrs.asdict(), gb.attrs.asdict(), where)
        ka, kb = set(ga.keys()), set(gb.keys())
        self.diffs += [f"{where}/{k}: only before" for k in sorted(ka - kb)]
        self.additions += [f"{where}/{k}: only after" for k in sorted(kb - ka)]
        for k in sorted(ka & kb):
            xa, xb = ga[k], gb[k]
            if isinstance(xa, zarr.Group):
                self.group(xa, xb, f"{where}/{k}")
                continue
            self.arrays += 1
            va, vb = xa[...], xb[...]
            if va.dtype != vb.dtype or va.shape != vb.shape:
                self.diffs.append(f"{where}/{k}: {va.dtype}{va.shape} before, {vb.dtype}{vb.shape} after")
            elif va.tobytes() != vb.tobytes() and not (va.dtype.kind == "O" and np.array_equal(va, vb)):
                bad = ~((va == vb) | (np.isnan(va) & np.isnan(vb))) if va.dtype.kind in "fc" else va != vb
                self.diffs.append(f"{where}/{k}: {int(np.sum(bad))} of {va.size} values differ")
            if xa.chunks != xb.chunks:
                self.diffs.append(f"{where}/{k}: chunks {xa.chunks} before, {xb.chunks} after")
            self.attrs(dict(xa.attrs), dict(xb.attrs), f"{where}/{k}")


def _stores(root: Path) -> list[Path]:
    found = sorted(p.relative_to(root) for p in root.rglob("*.zarr") if p.is_dir())
    return [s for s in found if not any(str(parent).endswith(".zarr") for parent in s.parents)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    ap.add_argument("--ignore-attr", nargs="*", default=[], metavar="NAME", help="attrs not compared")
    args = ap.parse_args(argv)
    c = Comparison(ALWAYS_IGNORED | set(args.ignore_attr))
    sa, sb = _stores(args.before), _stores(args.after)
    c.diffs += [f"store {s}: only before" for s in sorted(set(sa) - set(sb))]
    c.additions += [f"store {s}: only after" for s in sorted(set(sb) - set(sa))]
    for s in sorted(set(sa) & set(sb)):
        c.group(zarr.open_group(args.before / s, mode="r"), zarr.open_group(args.after / s, mode="r"), str(s))
    files = 0
    for p in sorted(args.before.rglob("*")):
        rel = p.relative_to(args.before)
        if p.is_file() and not any(str(parent).endswith(".zarr") for parent in rel.parents):
            files += 1
            q = args.after / rel
            if not q.exists() or p.read_bytes() != q.read_bytes():
                c.diffs.append(f"file {rel}: {'only before' if not q.exists() else 'bytes differ'}")
    print(f"{len(set(sa) & set(sb))} stores, {c.arrays} arrays compared value by value, {files} other files; "
          f"{len(c.diffs)} differences, {len(c.additions)} additions")
    for d in c.diffs:
        print("  " + d)
    if c.additions:
        print("additions:")
        for d in c.additions:
            print("  + " + d)
    return 1 if c.diffs else 0


if __name__ == "__main__":
    raise SystemExit(main())
