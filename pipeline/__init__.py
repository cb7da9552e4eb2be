"""Wear-test adhesion pipeline: TEM profiles, power-law fits, pull-off forces,
M-D-n / rigid inversion for W_A(h), and the adhesion range h.

All quantities inside the package are SI (m, N, Pa, J/m^2); units are converted
only at the edges (YAML configs, CSV reports, figures).

One sub-package a stage (``tem``, ``forces``, ``inversion``, ``adhesion_range``; ``fits``), each
with its science, ``io.py``, ``figures.py`` and ``stage.py``; ``mechanics`` the contact mechanics
they share; ``synth`` the synthetic data, imported by no stage.  The README's "Equation index"
maps each equation of the paper to its function.
"""

__version__ = "0.1.0"
