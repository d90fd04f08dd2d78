"""Infrastructure every side uses that is not the person model: an EGL context (``egl``), the
mesh rasteriser on it (``raster``), video files (``video``), atomic file writes (``atomic``)
and terminal progress bars (``progress``)."""
