"""Benchmarks behind ``facewire bench``: bandwidth, speed, quality."""
