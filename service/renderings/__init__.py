"""What answers become for command-and-control software, maps and files.

``points.py``: Cursor-on-Target events and GeoJSON of one located point with its error (a fix, an observer
session's state), and what the others share (one-sigma errors, ellipse polygons cut at the antimeridian, the
formats a request asks for); ``tracks.py``: the same for a network session's tracks; ``maps.py``: coverage
maps as GeoJSON, PNG, KMZ and GeoTIFF; ``tak.py``: the TAK feed that pushes CoT events off the request path;
``reports.py``: the command-line tools' Markdown, JSON and plots. This package imports nothing itself.
"""
