"""``python -m benchmarks``: the curated suite (benchmarks/suite.py)."""

from benchmarks.suite import main

raise SystemExit(main())
