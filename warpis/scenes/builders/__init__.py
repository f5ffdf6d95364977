"""The generators of the scenes bundled in ``meshes/``: library code behind the
``scripts/make_*.py`` command lines, which only parse their arguments and call in here.

* :mod:`.common` — what they share: mesh and TOML writing, receiver classification
  (lit, penumbra, umbra), Veach's plate geometry, the check that regenerated files match
  the committed ones;
* :mod:`.mesh_scenes` — the TOML scenes (``scripts/make_scenes.py``);
* :mod:`.mitsuba_scenes` — the Mitsuba 3 XML scenes (``scripts/make_mitsuba_scenes.py``);
* :mod:`.material_preview` — ``mitsuba-material-preview`` (``scripts/make_material_preview.py``).

Nothing here is imported by :mod:`warpis.scenes` itself; Mitsuba, an optional extra, is
imported only inside the functions that read a scene back or trace camera rays.
"""
