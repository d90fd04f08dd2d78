"""The person model shared by both hosts: the geometry vocabulary (``geometry``), landmarks and
their files (``landmarks``, ``landmark_files``), the generic head (``head/``), the mesh
(``mesh``), the volume morph and the rig (``morph``, ``rig``), texture regions and their draw
order (``regions``, ``draworder``), how a virtual camera frames a head (``framing``), the
``.fwm`` file (``modelfile``, its manifest ``manifest``, the model's field checks ``fields``,
its zip container ``archive``, array checks ``arrays``) and glTF (``gltf``). ``infra/`` holds
what is not the model: EGL, the rasteriser, video files, atomic writes, progress."""
