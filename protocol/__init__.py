"""Wire protocol: the fixed-size frame packet, control messages, packet logs, ZeroMQ transport.

Imports nothing else of facewire: both hosts depend on it.
"""
