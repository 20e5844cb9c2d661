"""Speed of the numpy PHY abstraction against Sionna SYS 2.2 on the same inputs.

    python -m benchmarks.link_sys [--users 2000] [--subcarriers 612] [--json out.json]

The numpy side always runs (link-level evaluations per second); the comparison needs the optional
extra ``sys-reference`` (Sionna SYS on PyTorch) and is reported as not installed without it. Inputs: random per-resource-
element SINRs ``[users, subcarriers]`` (one OFDM symbol, so both count N_RE = subcarriers), MCS
table 1, PDSCH BLER tables. Timed, best of ``--repeat`` runs, on the CPU:

- ``phy``: effective SINR (EESM), BLER, TBLER at a given MCS per user (Sionna ``PHYAbstraction``);
- ``illa``: inner-loop MCS selection for a 10 % TBLER target (Sionna
  ``InnerLoopLinkAdaptation``), which evaluates every MCS.

Sionna runs in double and in single precision; results are checked to agree before timing.
Prints the times and the ratios (Sionna time / numpy time) and writes them as JSON.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from simart_pipeline.link.link_adaptation import select_mcs_inner_loop
from simart_pipeline.link.phy_abstraction import PhyAbstraction


def _best_of(fn, repeat: int) -> float:
    fn()                                     # warm-up (lazy tables, allocator)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--users", type=int, default=2000, help="receivers x time steps")
    ap.add_argument("--subcarriers", type=int, default=612, help="resource elements per user")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="write the results here (default: stdout only)")
    args = ap.parse_args(argv)
    U, K = args.users, args.subcarriers
    rng = np.random.default_rng(args.seed)
    sinr = rng.exponential(size=(U, K)) * 10 ** rng.uniform(-0.5, 3.0, (U, 1))   # -5..30 dB
    phy = PhyAbstraction(num_re=K, mcs_table_index=1, category="pdsch")
    mcs = rng.choice(np.flatnonzero(phy.available), U)

    def numpy_phy():
        eff = phy.effective_sinr(sinr, mcs)
        return eff, *phy.bler(eff, mcs)

    def numpy_illa():
        return select_mcs_inner_loop(phy, sinr, 0.1)[0]

    results = dict(users=U, subcarriers=K, repeat=args.repeat, numpy_version=np.__version__)
    results["numpy_phy_s"] = _best_of(numpy_phy, args.repeat)
    results["numpy_illa_s"] = _best_of(numpy_illa, args.repeat)
    # One evaluation: a user's effective SINR (EESM over its resource elements), BLER and TBLER at
    # its MCS; one MCS selection evaluates every MCS of the table for one user.
    results["numpy_phy_evaluations_per_s"] = U / results["numpy_phy_s"]
    results["numpy_mcs_selections_per_s"] = U / results["numpy_illa_s"]
    try:
        import torch
        from sionna.sys import InnerLoopLinkAdaptation, PHYAbstraction
    except ImportError as exc:
        results["sionna_sys"] = f"not installed (pip install -e '.[sys-reference]'): {exc}"
        print(f"{U} users x {K} resource elements, MCS table 1: numpy PHY abstraction "
              f"{results['numpy_phy_evaluations_per_s']:.0f} evaluations/s, MCS selection "
              f"{results['numpy_mcs_selections_per_s']:.0f} users/s; Sionna SYS not installed, no comparison")
        return _write(results, args.json)
    results.update(torch_threads=torch.get_num_threads(), torch_version=torch.__version__)
    ref_eff, ref_bler, _ = numpy_phy()
    ref_mcs = numpy_illa()

    for precision, dtype in (("double", torch.float64), ("single", torch.float32)):
        t0 = time.perf_counter()
        sphy = PHYAbstraction(precision=precision)
        illa = InnerLoopLinkAdaptation(sphy, bler_target=0.1, precision=precision)
        results[f"sionna_{precision}_init_s"] = time.perf_counter() - t0
        # [batch = users, OFDM symbol, subcarrier, user, stream]
        s = torch.tensor(sinr[:, None, :, None, None], dtype=dtype)
        m = torch.tensor(mcs[:, None], dtype=torch.int32)

        def sionna_phy():
            return sphy(m, sinr=s, mcs_table_index=1, mcs_category=1)

        def sionna_illa():
            return illa(sinr=s, mcs_table_index=1, mcs_category=1)

        with torch.no_grad():
            _, _, s_eff, _, s_bler = sionna_phy()
            s_mcs = sionna_illa()[:, 0].numpy()
            eff_db = 10 * np.log10(np.clip(ref_eff, 1e-3, 1e3))
            results[f"sionna_{precision}_max_eff_diff_db"] = float(
                np.abs(eff_db - 10 * np.log10(s_eff[:, 0].double().numpy())).max())
            results[f"sionna_{precision}_max_bler_diff"] = float(
                np.abs(ref_bler - s_bler[:, 0].double().numpy()).max())
            results[f"sionna_{precision}_mcs_mismatches"] = int((s_mcs != ref_mcs).sum())
            results[f"sionna_{precision}_phy_s"] = _best_of(sionna_phy, args.repeat)
            results[f"sionna_{precision}_illa_s"] = _best_of(sionna_illa, args.repeat)
        for what in ("phy", "illa"):
            results[f"speedup_{what}_vs_sionna_{precision}"] = (
                results[f"sionna_{precision}_{what}_s"] / results[f"numpy_{what}_s"])

    print(f"{U} users x {K} resource elements, MCS table 1, torch threads "
          f"{results['torch_threads']}")
    print(f"{'':10s}{'numpy':>10s}{'sionna f64':>12s}{'sionna f32':>12s}"
          f"{'ratio f64':>11s}{'ratio f32':>11s}")
    for what in ("phy", "illa"):
        print(f"{what:10s}{results[f'numpy_{what}_s'] * 1e3:9.1f}ms"
              f"{results[f'sionna_double_{what}_s'] * 1e3:11.1f}ms"
              f"{results[f'sionna_single_{what}_s'] * 1e3:11.1f}ms"
              f"{results[f'speedup_{what}_vs_sionna_double']:10.2f}x"
              f"{results[f'speedup_{what}_vs_sionna_single']:10.2f}x")
    return _write(results, args.json)


def _write(results: dict, path: str | None) -> int:
    print(json.dumps(results, indent=1))
    if path:
        with open(path, "w", encoding="utf-8") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
