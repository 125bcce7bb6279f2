"""From a drawing to a laser job, sans I/O: bytes of an SVG, DXF or image go in, G-code text
comes out.

import (:mod:`.svg`, :mod:`.dxf`, :mod:`.image`) -> a :class:`~.model.Drawing` of layers
(one per colour, one per image) -> toolpaths (:mod:`.order`: inner shapes first, nearest
neighbour; :mod:`.hatch`: fills; :mod:`.raster`: images) -> G-code (:mod:`.emit`).
:func:`.job.make_job` is the whole way. Nothing here touches a file, a socket or the loop:
the CLI (``motiond import``) and the JSON API read and store, and run this in a worker.
Units: mm in the machine's frame (X right, Y up, the drawing's bottom-left at 0,0), speeds in
mm/min, power in percent of the laser's maximum S. Imports only :mod:`server.errors`; the
parsers come from the ``[cam]`` extra (svgelements, ezdxf, Pillow, shapely).
"""
