"""Helpers for the test suite and the benchmarks: synthetic scenes and datasets, tiny model presets,
a headless browser, the project's scripts as modules. Importable from the installed package, so
benchmarks and scripts need no path edits."""
