"""arpz's benchmarks: ``python -m benchmarks`` runs the curated suite (benchmarks/suite.py, its
entries in benchmarks/entries.py, its references in benchmarks/RESULTS.md); every script also runs
on its own (``python benchmarks/NAME.py --help``); benchmarks/investigations/ holds the ones that
answered one question."""
