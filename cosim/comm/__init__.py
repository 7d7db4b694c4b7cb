"""V2X communication links per tick (docs/comm.md).

- :mod:`cosim.comm.channel`: 3GPP path loss and shadow fading, one function per model and state;
- :mod:`cosim.comm.phy`: noise, link budget, packet error rate, rates, delay;
- :mod:`cosim.comm.los`: line of sight through the ray-cast scene (LOS, NLOSv, NLOS);
- :mod:`cosim.comm.links`: the link model (:func:`~cosim.comm.links.compute_links`,
  :class:`~cosim.comm.links.LinkModel`);
- :mod:`cosim.comm.message`: the ``/comm/links`` topic (schema, payload, decoding);
- :mod:`cosim.io.comm_report`: ``cosim comm``: summary per link type and plots.

Importing this package loads nothing heavy; the link model needs a ray backend (through its scene).
"""
