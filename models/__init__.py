"""The person model shared by both hosts: landmarks, generic head, volume morph, fitting, file format."""
