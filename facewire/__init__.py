"""facewire: the one installed package. The design card's folders install beneath it
(``facewire.protocol``, ``models``, ``sender``, ``receiver``, ``bench``; docs/DESIGN.md §1);
this folder holds the command on top of them: argument parsing and dispatch (``cli``), how
every command prints (``report``), ``facewire demo`` (``demo``) and its scripted performer
(``performer``)."""
