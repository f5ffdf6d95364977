"""Warp kernels and the launch loop, in the order a trial uses them.

* ``rng`` — counter-based random numbers (and their numpy twin);
* ``patterns`` — where the primary samples fall (the ``PATTERNS`` registry);
* ``warps`` — square → hemisphere/triangle maps;
* ``techniques`` — direction sampling and pdfs (the ``TECHNIQUES`` registry);
* ``integrand`` — the BRDF and f at a receiver (the ``MATERIALS`` registry);
* ``estimators`` — one trial of PATTERN:COMBINER[=VALUE]:TECH[+TECH...] (the ``COMBINERS`` registry);
* ``evaluate`` — f and every technique's pdf at dense points (the quadrature's kernel);
* ``registered`` — those kernels rebuilt around user techniques and patterns, in one module;
* ``device`` — a scene uploaded to a Warp device, cached by content digest and device;
* ``engine`` — the launch loop: trials (or their moments) over receivers.
"""
