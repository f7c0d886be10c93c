"""Benchmark suites run from the command line (``evgs bench ...``); the micro-benchmarks are in
``benches/``."""
