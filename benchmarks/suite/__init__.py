"""The sections of benchmarks/gpu_suite.py (its CLI and records stay there): shared timing tools, the models
it times, and one module per section (parity, train step and memory, render, components)."""
