"""The render host: receive loop, loss concealment, 3D-texture rendering, outputs."""
