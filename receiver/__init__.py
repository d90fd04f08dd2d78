"""The render host: the receive loop (``receiver``), model acquisition and cache (``acquire``,
``modelcache``), statistics (``stats``), playout and loss concealment (``playout``),
3D-texture rendering (``scene``, ``views``, ``render``), outputs (``output``), replay of a
packet log (``replay``) and the live view (``liveview``)."""
