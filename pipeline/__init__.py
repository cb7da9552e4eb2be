"""Wear-test adhesion pipeline: TEM profiles, power-law fits, pull-off forces,
M-D-n / rigid inversion for W_A(h), and the adhesion range h.

All quantities inside the package are SI (m, N, Pa, J/m^2); units are converted
only at the edges (YAML configs, CSV reports, figures).
"""

__version__ = "0.1.0"
