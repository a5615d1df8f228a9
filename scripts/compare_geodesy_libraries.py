"""Speed and round-trip accuracy of pymap3d, pyproj and core.geodesy (the choice in core/geodesy.py).

Run: .venv/bin/python scripts/compare_geodesy_libraries.py   (pyproj comes with the dev extras)
"""

from __future__ import annotations

import time

import numpy as np
import pymap3d
import pyproj

from core import geodesy


def best_of(f, repeats=5):
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - start)
    return best


def main(n: int = 100_000) -> None:
    rng = np.random.default_rng(1)
    forward = pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    inverse = pyproj.Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)
    lat = rng.uniform(-90, 90, n)
    lon = rng.uniform(-180, 180, n)
    print(f"forward, {n} points: pymap3d {best_of(lambda: pymap3d.geodetic2ecef(lat, lon, lat * 0)):.4f} s, "
          f"pyproj {best_of(lambda: forward.transform(lon, lat, lat * 0)):.4f} s; one point: "
          f"pymap3d {best_of(lambda: pymap3d.geodetic2ecef(34.5, 108.9, 8000.0), 1000) * 1e6:.1f} us, "
          f"pyproj {best_of(lambda: forward.transform(108.9, 34.5, 8000.0), 1000) * 1e6:.1f} us")
    print("worst ECEF round-trip error (m) by altitude ceiling:   pymap3d     pyproj   core.geodesy")
    for ceiling in (1e3, 1e5, 1e6, 2e7):
        alt = rng.uniform(-1e3, ceiling, n)
        x, y, z = pymap3d.geodetic2ecef(lat, lon, alt)
        p = np.stack([x, y, z], axis=-1)
        a = np.stack(pymap3d.geodetic2ecef(*pymap3d.ecef2geodetic(x, y, z)), axis=-1)
        lo, la, al = inverse.transform(x, y, z)
        b = np.stack(forward.transform(lo, la, al), axis=-1)
        c = geodesy.geodetic_to_ecef(*geodesy.ecef_to_geodetic(p))
        errors = [np.max(np.linalg.norm(q - p, axis=-1)) for q in (a, b, c)]
        print(f"  {ceiling:10.0e} m {errors[0]:12.2e} {errors[1]:10.2e} {errors[2]:12.2e}")


if __name__ == "__main__":
    main()
