"""``python -m benchmarks [--quick] --out DIR``: every stage benchmark, one report (benchmarks.bench)."""

from benchmarks.bench import main

raise SystemExit(main())
