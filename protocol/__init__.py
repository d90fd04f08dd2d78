"""Wire protocol: the fixed-size frame packet (``packet``), control messages (``control``),
packet logs (``log``), ZeroMQ transport (``transport``), CURVE key folders (``keys``), the
relay (``relay``), the packet rate contract (``rate``) and the error base (``errors``).

Imports nothing else of facewire: both hosts depend on it.
"""
