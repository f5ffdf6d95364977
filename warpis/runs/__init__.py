"""Runs that measure and predict: one cell pipeline, and the commands built on it.

* ``cell`` — a cell measured, every prediction attached, the verdict rules (once);
* ``verify`` — one scene, default estimators, ``verify.json``;
* ``study`` — study files, resumable ``results.csv``, ``summary.json``, figures;
* ``outdir`` — output folders: one writer at a time, atomic files.
"""
