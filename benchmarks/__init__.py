"""Speed, memory and accuracy benchmarks. Run all with ``python -m benchmarks [--quick]``."""
