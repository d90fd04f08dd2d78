"""Headless OpenGL through EGL: the system check behind ``facewire check`` and every renderer.

On Debian/Ubuntu the system packages are ``libegl1 libgl1 libgl1-mesa-dri`` (Mesa's llvmpipe
renders on the CPU when there is no GPU). Without them moderngl cannot open a context, so we
check first and say which packages are missing instead of failing deep inside a render.
"""

from __future__ import annotations

import ctypes.util

SYSTEM_PACKAGES = "libegl1 libgl1 libgl1-mesa-dri"


class EGLUnavailable(RuntimeError):
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
        ctx = moderngl.create_standalone_context(backend="egl")
    except Exception as exc:  # moderngl raises plain Exception for context failures
        raise EGLUnavailable(
            f"could not create an EGL OpenGL context ({exc}). On Debian/Ubuntu install "
            f"Mesa's drivers with: apt-get install -y {SYSTEM_PACKAGES}") from exc
    try:
        return f"OpenGL {ctx.version_code // 100}.{ctx.version_code % 100 // 10} " \
               f"through EGL on {ctx.info['GL_RENDERER']}"
    finally:
        ctx.release()
