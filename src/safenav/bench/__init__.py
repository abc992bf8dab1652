"""Benchmarks behind ``safenav bench``: env throughput, update throughput, onboard latency."""
