"""The one simulated clock: int64 nanoseconds from the start of a session.

Each stream samples the clock at its own rate. Sample ``i`` of a stream at rate ``r`` lies at
``floor(i * 1e9 / r)`` ns, computed in exact rational arithmetic, so two streams whose rates share
instants share them exactly (a 10 Hz and a 2 Hz stream coincide every 500 000 000 ns), and a rate
with no integer-nanosecond period (30 Hz) has at most 1 ns of jitter, never drift.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

NS_PER_S = 1_000_000_000


def seconds_to_ns(seconds: float | str) -> int:
    """Seconds (decimal, as written in a config or a CSV cell) to integer nanoseconds: exact for up
    to nine decimals, else rounded to the nearest nanosecond (ties to even)."""
    return round(Fraction(str(seconds).strip()) * NS_PER_S)


def sample_times_ns(duration_s: float, rate_hz: float, start_ns: int = 0) -> np.ndarray:
    """Sample instants of a stream at ``rate_hz`` within ``[start_ns, duration]`` inclusive.

    :returns: ``[n]`` int64 ns, strictly increasing.
    """
    rate = Fraction(str(rate_hz))
    end_ns = seconds_to_ns(duration_s)
    if rate <= 0:
        raise ValueError(f"rate must be positive, got {rate_hz}")
    n = int((end_ns - start_ns) * rate // NS_PER_S) + 1
    i = np.arange(max(n, 0), dtype=object)
    # Exact rational floor: (i * 1e9 * den) // num, in Python ints, then int64.
    t = start_ns + (i * NS_PER_S * rate.denominator) // rate.numerator
    return t.astype(np.int64)


def ns_to_seconds(t_ns: np.ndarray) -> np.ndarray:
    """int64 ns to float64 s (for physics); the stored coordinate stays int64."""
    return np.asarray(t_ns, dtype=np.int64).astype(np.float64) / NS_PER_S
