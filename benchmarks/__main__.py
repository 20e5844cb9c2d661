"""``python -m benchmarks [--quick] --out DIR``: every stage benchmark, one report (benchmarks.bench).

It is ``simart bench ARGS``: one parser, one code path (the CLI imports benchmarks.bench, not the
other way round)."""

import sys

from simart_pipeline.cli import main

raise SystemExit(main(["bench", *sys.argv[1:]]))
