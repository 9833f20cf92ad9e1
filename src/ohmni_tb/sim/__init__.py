"""Virtual firmware for every device on the Ohmni bus, and the simulated line.

``line`` (wire timing, collisions, faults, dispatch), ``transport`` (the host's end),
``url`` (``sim://`` options), ``robot`` (every device of one robot), the devices
(``drive``, ``core``, ``servo``, ``worm_neck``), ``clock`` (virtual time) and ``pty``
(serving on a pseudo-terminal).
"""
