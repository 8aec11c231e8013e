"""Plane geometry shared by every layer: polylines and rings (``polyline``), one definition
each, tested against float64 reference loops (tests/test_geometry_polyline.py)."""
