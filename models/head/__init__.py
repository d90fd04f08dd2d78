"""The generic head: a procedural, closed, mirror-symmetric triangle mesh of an adult head.

Everything is built from the formulas in this package; no scanned or third-party mesh is used.

Frame (as ``models/mesh.py``): mm, x toward the person's left, y up, z out of the face. The
origin is on the midsagittal plane (x = 0) at the height of the eye corners (y = 0), about
halfway between the forehead and the back of the head (z = 0). Average adult dimensions: outer
eye corners 91 mm apart, inner 34 mm, pupils 63 mm; head breadth 152 mm, chin to vertex
232 mm, nose tip to the back of the head 217 mm; mouth 49 mm wide; nose tip 26 mm in front of
the inner eye corners (35 mm in front of the outer ones). About 11 200 vertices and 22 100
triangles.

The build, in the order of its parts (each module states its part of the math):

- ``primitives``: smooth minimum, smoothstep, bumps and ellipsoids that the fields are made of;
- ``anatomy``: the designed features: eyes, eyelid margins, lip lines, landmark positions;
- ``skin``: the skin as the zero set of a field (a loft, a relief, eyelids, ears, neck);
- ``rays``: the skin parameterised by ray directions, and ray casting;
- ``features``: the samples placed by design (openings, rows beside them, landmarks, phantoms);
- ``sampling``: the free samples (Poisson-disk thinning, Lloyd relaxation);
- ``sphere``: the spherical Delaunay triangulation, Gabriel circles, edge recovery, holes;
- ``halfskin``: the triangulated skin of the half x >= 0, its openings cut out;
- ``uvlayout``: the texture layout;
- ``inserts``: what closes the openings (socket cups, mouth cavity) and the eyeballs;
- ``tags``: SKIN, SCALP and EAR;
- ``assembly``: the half mirrored and welded; landmarks, phantoms and the mirror map.

Its interface is ``generic_head()`` and ``mirror_map()``; the design constants that tests
and the texture regions read live in ``anatomy`` (the eye) and ``uvlayout``.
"""

from facewire.models.head.assembly import generic_head, mirror_map

__all__ = ["generic_head", "mirror_map"]
