"""The one way to reach Mitsuba and Sionna RT: variant choice and the libLLVM preflight.

Sionna RT needs a Mitsuba ``*_ad_mono_polarized`` variant. On a machine with a CUDA GPU the
``cuda`` variant is used, otherwise drjit's LLVM backend, which needs libLLVM >= 17 (LLVM 14 and 15
abort with ``Cannot select ... fmaximum``). The sensor renderer uses the same variant, so one process
never switches variants.
"""

from __future__ import annotations

import ctypes.util
import glob
import os
import re
from functools import lru_cache

MIN_LLVM = 17
LLVM_FIX = ("install libLLVM 17 or later, e.g. on Debian/Ubuntu `sudo apt-get install libllvm19`, "
            "or point DRJIT_LIBLLVM_PATH at a libLLVM.so of version >= 17")


class PreflightError(RuntimeError):
    pass


def _llvm_candidates() -> list[tuple[int, str]]:
    found = []
    explicit = os.environ.get("DRJIT_LIBLLVM_PATH")
    if explicit:
        m = re.search(r"LLVM[-.]?(\d+)", os.path.basename(explicit))
        found.append((int(m.group(1)) if m else MIN_LLVM, explicit))
    for d in ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
              "/usr/local/lib", "/opt/homebrew/opt/llvm/lib"):
        for path in glob.glob(os.path.join(d, "libLLVM*.so*")) + glob.glob(os.path.join(d, "llvm-*/lib/libLLVM*.so*")):
            m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(path))
            if m:
                found.append((int(m.group(1)), path))
    name = ctypes.util.find_library("LLVM")
    if name:
        m = re.search(r"(\d+)", name)
        found.append((int(m.group(1)) if m else 0, name))
    return sorted(set(found), key=lambda c: (c[0], c[1].startswith("/")), reverse=True)


def cuda_available() -> bool:
    return bool(ctypes.util.find_library("cuda")) or os.path.exists("/dev/nvidia0")


def preflight() -> str:
    """Return a one-line description of the backend to use, or raise :class:`PreflightError`."""
    if cuda_available():
        return "cuda"
    cands = _llvm_candidates()
    good = [c for c in cands if c[0] >= MIN_LLVM]
    if not good:
        seen = ", ".join(f"LLVM {v} ({p})" for v, p in cands) or "none"
        raise PreflightError(f"drjit's LLVM backend needs libLLVM >= {MIN_LLVM}; found: {seen}. Fix: {LLVM_FIX}")
    version, path = good[0]
    # drjit picks the first libLLVM it finds; name the good one so an older one never wins.
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", path)
    return f"llvm (libLLVM {version}: {os.environ['DRJIT_LIBLLVM_PATH']})"


@lru_cache(maxsize=1)
def init() -> str:
    """Check the machine, select the Mitsuba variant, import Sionna RT; returns the variant name."""
    backend = preflight()
    import mitsuba as mi

    variant = "cuda_ad_mono_polarized" if backend == "cuda" else "llvm_ad_mono_polarized"
    try:
        mi.set_variant(variant)
    except Exception:
        if variant.startswith("cuda"):
            variant = "llvm_ad_mono_polarized"
            mi.set_variant(variant)
        else:
            raise
    import sionna.rt  # noqa: F401  (registers Sionna's Mitsuba plugins)

    from simart_pipeline import sionna_fixes  # imports drjit: only once the variant is set

    sionna_fixes.apply()
    return variant


def release_memory_cache() -> None:
    """Hands Dr.Jit's cache of freed blocks back to the system. Dr.Jit keeps a freed block for a
    later allocation of the same size; work whose buffers change size from call to call (PathSolver
    sizes them by receivers, samples and candidates) leaves a process holding the high-water mark of
    every size it has seen (``benchmarks.ckm_solver`` reached 22 GB; after one of Munich's
    every-mechanism reference batches 5.8 GB were resident, 1.25 GB after this). A call of the same
    shape as the last one gains from the cache instead (the one-pass at 1e7 rays takes 3 s longer
    on 2 cores after a release, its pages faulted in again), so only callers of the first kind use it."""
    import drjit as dr

    dr.flush_malloc_cache()


def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("simart-pipeline", "sionna-rt", "mitsuba", "drjit", "numpy", "xarray", "zarr",
                "dagster", "trimesh", "scipy"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            pass
    return out
