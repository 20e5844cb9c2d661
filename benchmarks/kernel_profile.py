"""Where the one-pass CKM's time goes, kernel by kernel, charged to the function that launched it.

    python -m benchmarks.kernel_profile [--scene street_canyon] [--rays 1e7] [--model full|first_order]
                                        [--polarization V|none] [--top 40] [--out FILE.json]

Dr.Jit traces lazily and launches a kernel where a value is first needed, so a Python profile
charges a kernel to whichever line waits for it, and cannot tell a kernel that recomputes what
another one computed already. This runs one warm call of the one-pass (the ``all`` set of
:mod:`benchmarks.ckm_solver` on the scene, through :class:`benchmarks.ckm_variants.SceneRuns`) with
Dr.Jit's kernel history on and every method of the tracer and the diffraction sampler (and the
shoot-and-bounce module's helpers) wrapped, so that each kernel is charged to the innermost wrapped
function running when it was launched (the last three of the stack name it). Rows: total execution
time, launches, lanes and operation count per (function, operation count), largest first.

The sign of a lazy expression evaluated twice: two kernels charged to one function over the same
lanes with similar operation counts (docs/ckm-one-pass.md, "Pitfalls met"). Execution times are the
kernels' own (``execution_time``): host work between them (numpy, pandas) is not in them.
"""

from __future__ import annotations

import argparse
import collections
import functools
import inspect
import json
import tempfile
from pathlib import Path

STACK_DEPTH = 3  # the innermost functions that name a row


class KernelLedger:
    """Kernel history charged to a stack of labels: :meth:`wrap` a function, and every kernel
    launched while it runs (and no wrapped function inside it does) is charged to it."""

    def __init__(self, dr):
        self.dr = dr
        self.stack = ["(outside)"]
        self.rows: dict[tuple[str, int], list] = collections.defaultdict(lambda: [0, 0.0, 0])

    def flush(self) -> None:
        """Charge the kernels launched since the last flush to the current stack."""
        for e in self.dr.kernel_history():
            if str(e.get("type")).endswith("JIT"):
                r = self.rows[("/".join(self.stack[-STACK_DEPTH:]), int(e.get("operation_count", 0)))]
                r[0] += 1
                r[1] += float(e.get("execution_time", 0.0))
                r[2] += int(e.get("size", 0))

    def wrap(self, fn, label: str):
        @functools.wraps(fn)
        def charged(*args, **kwargs):
            self.flush()
            self.stack.append(label)
            try:
                return fn(*args, **kwargs)
            finally:
                self.flush()
                self.stack.pop()
        return charged

    def table(self) -> list[dict]:
        return [{"function": k[0], "operations": k[1], "launches": v[0], "ms": round(v[1], 3), "lanes": v[2]}
                for k, v in sorted(self.rows.items(), key=lambda kv: -kv[1][1])]


def _wrap_all(ledger: KernelLedger, monkey: list) -> None:
    """Every method of the tracer and the diffraction sampler, and the shoot-and-bounce helpers
    that evaluate, wrapped; ``monkey`` collects (owner, name, original) to undo it."""
    from simart_pipeline.ckm import diffraction as df
    from simart_pipeline.ckm import shoot_bounce as sb

    def put(owner, name, label):
        original = getattr(owner, name)
        monkey.append((owner, name, original))
        setattr(owner, name, ledger.wrap(original, label))

    for cls in (sb.Tracer, df.DiffractionSampler):
        for name, fn in list(vars(cls).items()):
            if inspect.isfunction(fn) and not name.startswith("__"):
                put(cls, name, f"{cls.__name__}.{name}")
    for name in ("_kept", "_compact", "_unique_keys", "_cumulative_lanes"):
        put(sb, name, name)
    # diffraction imported _unique_keys by name: the wrapped one there too
    put(df, "_unique_keys", "_unique_keys")


def profile(scene: str, rays: int, full_model: bool = True, polarization: str | None = None) -> dict:
    """One compiling call, then one call with the kernel history charged (:class:`KernelLedger`)."""
    import drjit as dr

    from benchmarks.ckm_variants import SceneRuns

    with tempfile.TemporaryDirectory(prefix="kernel-profile-") as tmp:
        s = SceneRuns(scene, Path(tmp))
        call = s.one_pass(rays, polarization, diffraction_with_reflections=full_model)
        call()  # compiles
        ledger, monkey = KernelLedger(dr), []
        _wrap_all(ledger, monkey)
        try:
            dr.kernel_history()  # nothing of before
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            call()
            ledger.flush()
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, False)
            for owner, name, original in reversed(monkey):
                setattr(owner, name, original)
    rows = ledger.table()
    return {"scene": scene, "rays": rays, "model": "full" if full_model else "first_order",
            "polarization": polarization, "kernel_ms": round(sum(r["ms"] for r in rows), 1),
            "kernels": sum(r["launches"] for r in rows), "rows": rows}


def main(argv=None) -> int:
    from benchmarks import ckm_solver as cs

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="street_canyon", choices=list(cs.SCENES))
    ap.add_argument("--rays", type=float, default=1e7)
    ap.add_argument("--model", choices=("full", "first_order"), default="full",
                    help="full: every chain; first_order: RadioMapSolver's diffraction model")
    ap.add_argument("--polarization", choices=("V", "none"), default="none")
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--out", type=Path, help="write the whole table as JSON")
    a = ap.parse_args(argv)
    r = profile(a.scene, int(a.rays), a.model == "full", None if a.polarization == "none" else a.polarization)
    print(f"{a.scene}, {int(a.rays):.0e} rays, {r['model']}: {r['kernels']} kernels, {r['kernel_ms']:.0f} ms")
    for row in r["rows"][:a.top]:
        print(f"{row['ms']:9.1f} ms {row['launches']:4d} x {row['lanes'] / 1e6:8.2f} M lanes  ops {row['operations']:5d}  "
              f"{row['function']}")
    if a.out:
        a.out.write_text(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
