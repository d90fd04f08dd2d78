"""The person model shared by both hosts: landmarks, generic head, volume morph, texture
regions, file format; infra/ holds what is not the model (EGL, rasteriser, video files)."""
