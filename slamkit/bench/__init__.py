"""slamkit.bench: benchmarks behind ``slamkit bench ...`` (each module exposes add_*_arguments / run_*)."""
