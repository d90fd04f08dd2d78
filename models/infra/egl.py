"""Headless OpenGL through EGL: the system check behind ``facewire check`` and every renderer.

Several contexts live in one process (a renderer, the texture projector), and EGL has one
*current* context per thread, so every method that issues GL calls makes its own context
current first (``in_context``); leaving it makes none current, so no caller may rely on a
context staying current between calls.

On Debian/Ubuntu the system packages are ``libegl1 libgl1 libgl1-mesa-dri`` (Mesa's llvmpipe
renders on the CPU when there is no GPU). Without them moderngl cannot open a context, so we
check first and say which packages are missing instead of failing deep inside a render.
"""

from __future__ import annotations

import ctypes.util
import functools
from collections.abc import Callable
from typing import Any, TypeVar

from facewire.protocol.errors import FacewireError

SYSTEM_PACKAGES = "libegl1 libgl1 libgl1-mesa-dri"

_Method = TypeVar("_Method", bound=Callable[..., Any])


class EGLUnavailable(FacewireError, RuntimeError):
    """Headless OpenGL cannot be used on this machine; the message says how to fix it."""


def check_egl() -> str:
    """Open a headless OpenGL context through EGL and describe it.

    Returns:
        A one-line description: renderer and OpenGL version.

    Raises:
        EGLUnavailable: the EGL/GL libraries are missing or no context can be created.
    """
    missing = [lib for lib in ("EGL", "GL") if ctypes.util.find_library(lib) is None]
    if missing:
        raise EGLUnavailable(
            f"headless OpenGL is not available: lib{' and lib'.join(missing)} not found. "
            f"On Debian/Ubuntu install them with: apt-get install -y {SYSTEM_PACKAGES}")
    import moderngl

    try:
        ctx = moderngl.create_standalone_context(
            backend="egl")  # type: ignore[arg-type]  # stub: **settings: dict
    except Exception as exc:  # moderngl raises plain Exception for context failures
        raise EGLUnavailable(
            f"could not create an EGL OpenGL context ({exc}). On Debian/Ubuntu install "
            f"Mesa's drivers with: apt-get install -y {SYSTEM_PACKAGES}") from exc
    try:
        return f"OpenGL {ctx.version_code // 100}.{ctx.version_code % 100 // 10} " \
               f"through EGL on {ctx.info['GL_RENDERER']}"
    finally:
        ctx.release()


def create_context() -> Any:
    """A new headless OpenGL 3.3 ``moderngl.Context`` through EGL.

    Raises:
        EGLUnavailable: headless OpenGL cannot be used (the message says how to fix it).
    """
    import moderngl

    try:
        return moderngl.create_standalone_context(
            backend="egl", require=330)  # type: ignore[arg-type]  # stub: **settings: dict
    except Exception as exc:  # moderngl raises plain Exception for context failures
        check_egl()  # raises EGLUnavailable naming the missing system packages
        raise EGLUnavailable(f"could not create an OpenGL 3.3 context through EGL "
                             f"({exc})") from exc


def in_context(method: _Method) -> _Method:
    """Decorate a method of an object holding ``self._ctx`` to run with that context current."""
    @functools.wraps(method)
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        with self._ctx:
            return method(self, *args, **kwargs)
    return wrapper  # type: ignore[return-value]
