"""What the measurements are held against: closed forms, references, quadrature, theory.

* ``closed_form`` — Lambert's irradiance from polygons, an occlusion-free oracle;
* ``reference`` — F at a receiver to a stated precision;
* ``quadrature`` — dense u-space evaluation: exact variances, moments, the optimal α;
* ``memo`` — those exact variances and moments kept on disk by content, for the next process;
* ``theory`` — every predicted-variance form of the seed (``FORMS``), printed and exact.

Sample moments and intervals are :mod:`warpis.stats`'s (the ground floor: the kernels use them).
"""
