"""Writes bracket.dxf (run from this folder): a plate with every entity kind motiond cuts.

Units: the header says millimetres. Layer CUT (red): the outline, a LWPOLYLINE with two
bulged (arc) corners; layer HOLES (blue): circles and an ARC+LINE slot; layer ENGRAVE
(green): a SPLINE and an ELLIPSE. The same geometry drawn as SVG is bracket_reference.svg.
"""

import ezdxf

doc = ezdxf.new("R2010", setup=False)
doc.header["$INSUNITS"] = 4  # mm
doc.layers.add("CUT", color=1)
doc.layers.add("HOLES", color=5)
doc.layers.add("ENGRAVE", color=3)
msp = doc.modelspace()
# 80 x 50 plate; the top corners rounded by bulges (bulge 0.414... = a 90 degree arc)
bulge = 0.41421356237
msp.add_lwpolyline([(0, 0, 0), (80, 0, 0), (80, 40, bulge), (70, 50, 0), (10, 50, bulge),
                    (0, 40, 0)], format="xyb", close=True, dxfattribs={"layer": "CUT"})
msp.add_circle((15, 15), 5, dxfattribs={"layer": "HOLES"})
msp.add_circle((65, 15), 5, dxfattribs={"layer": "HOLES"})
# a slot: two half circles joined by lines, centre (40, 35), 20 long, 6 wide
msp.add_line((34, 32), (46, 32), dxfattribs={"layer": "HOLES"})
msp.add_arc((46, 35), 3, -90, 90, dxfattribs={"layer": "HOLES"})
msp.add_line((46, 38), (34, 38), dxfattribs={"layer": "HOLES"})
msp.add_arc((34, 35), 3, 90, 270, dxfattribs={"layer": "HOLES"})
# a clamped cubic B-spline with four control points: the Bezier C 32,26 40,18 48,26
msp.add_open_spline([(25, 20), (32, 26), (40, 18), (48, 26)], degree=3,
                    dxfattribs={"layer": "ENGRAVE"})
msp.add_ellipse((40, 10), major_axis=(8, 0), ratio=0.5, dxfattribs={"layer": "ENGRAVE"})
doc.saveas("bracket.dxf")
