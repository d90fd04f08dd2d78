"""``FacewireError``: the one base of every error facewire raises on purpose.

The rule. Every failure a user can cause (a bad or missing file, a bad argument, a network
peer that misbehaves or is not there, a missing camera or a system without headless OpenGL)
is raised as a subclass of ``FacewireError`` whose message alone tells the user what went
wrong and where: it names the file, the field, the address or the device. The ``facewire``
command catches ``FacewireError`` and prints ``facewire: MESSAGE`` as one line on stderr,
with exit status 2 and no traceback; anything else that escapes is a bug in facewire, and
its traceback is what a bug report needs.

A module's error class may keep a standard exception as a second base (``ValueError``,
``OSError``, ``RuntimeError``) where callers catch that one, e.g.
``class PacketError(FacewireError, ValueError)``.

It lives in ``protocol`` because ``protocol`` imports nothing else of ours and every other
part may import it.
"""

from __future__ import annotations


class FacewireError(Exception):
    """A failure the user can act on; the message names what failed (module docstring)."""
