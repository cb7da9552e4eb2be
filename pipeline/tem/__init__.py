"""Stage 1: side-view TEM images of AFM tips -> sub-pixel apex profiles z(r).

Modules: ``reading`` (TIFF/PNG/JPEG/DM3/DM4 + pixel size), ``projection``
(projected thickness of an axisymmetric tip, Beer-Lambert contrast), ``edges``
(coarse tip location and model-based sub-pixel silhouette), ``profiles``
(tip frame, axis, apex, flanks z(r), asymmetry), ``figures`` and ``stage``.
"""
