"""What the measurements are held against: statistics, closed forms, references, theory.

* ``stats`` — sample moments, the fourth-moment variance interval, slopes;
* ``closed_form`` — Lambert's irradiance from polygons, an occlusion-free oracle;
* ``reference`` — F at a receiver to a stated precision;
* ``theory`` — every predicted-variance form of the seed (``FORMS``), printed and exact.
"""
