"""The camera host: capture (``capture``, ``framethread``), tracking (``tracker``), pose and
lift (``pose``, ``lift``), heuristics (``heuristics``), appearance sampling and
classification (``appearance``, ``classify``), packing (``pack``), one frame to one packet
(``pipeline``), the send loop (``sender``); and enrollment, a person's model from a video
(``enroll/``)."""
