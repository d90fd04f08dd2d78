"""Benchmarks behind ``facewire bench``: bandwidth (``bandwidth``), speed (``speed``, its live
part ``loopback``), quality (``quality``, with ``geometry``, ``fidelity``, ``reference`` and
``qplot``) on the tuning or evaluation clips (``clips``), fan-out (``fanout``, its viewer
processes ``viewers`` and its page run ``pageview``, in headless Chromium driven by
``chromium``); a process's CPU and memory from ``/proc`` (``procfs``); and ``facewire
inspect`` (``inspect``)."""
