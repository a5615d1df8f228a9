"""One contract for every registered estimator.

Every method in :data:`core.estimators.REGISTRY` (and every CTLS variant) is
run on a scene that gives it the measurement mix it needs: the generic
4-station 3D bearing scene by default, an azimuth-only variant with the
target altitude known for the azimuth-only methods, bearings plus ranges for
``angle_range``. A method registered later gets the default scene; if that
scene cannot serve it (it raises ``TooFewMeasurements``) it is skipped with a
message asking for an entry in :data:`SCENES`.

The contract: noise-free data give the target to 1e-6 of the scene's size;
re-ordering stations and measurements, or moving the whole scene 500 km east
(longitudes shifted, so the geometry is unchanged) or 500 km in a local
plane, changes neither the fix nor its covariance; one line of sight without
a range never gives a fix; and each method's documented failures happen with
the documented error and message.
"""

from __future__ import annotations

import numpy as np
import pytest

from core.errors import InvalidInput, LocalizationError, TooFewMeasurements, UnobservableGeometry
from core.estimators import REGISTRY, SolveOptions, solve
from core.problem.frame import LocalPoint

from core.simulation import scenarios as sc

#: Scenes for methods that need other than the generic 3D bearing scene.
SCENES = {
    "taylor_wls": sc.generic_azimuth_only,
    "tls": sc.generic_azimuth_only,
    "ctls": sc.generic_azimuth_only,
    "angle_range": sc.generic_angle_range,
}
VARIANTS = {"ctls": ("newton", "projected")}
CASES = [(name, variant) for name in sorted(REGISTRY) for variant in VARIANTS.get(name, (None,))]
IDS = [name if variant is None else f"{name}-{variant}" for name, variant in CASES]

#: 500 km along the parallel at the generic scene's latitude (34.5 deg).
SHIFT_LON_DEG = 500.0 / (111.32 * np.cos(np.deg2rad(34.5)))
RELATIVE = 1e-6


def scene_for(name: str) -> sc.Scene:
    return SCENES.get(name, sc.generic_3d)()


def as_local(scene: sc.Scene) -> sc.Scene:
    """The scene in a flat local plane: stations and target at their ENU in the geodetic frame."""
    template = scene.template()
    stations = tuple((sid, LocalPoint(*map(float, template.stations_enu_m[i])))
                     for i, (sid, _) in enumerate(scene.stations))
    target = LocalPoint(*map(float, scene.target_enu_m(template)))
    altitude = None if scene.altitude_m is None else target.up_m
    return sc.Scene(scene.name + " (local)", stations, scene.sensors, target, altitude, scene.sigma_known)


def scale_m(problem, target_enu_m) -> float:
    return float(np.mean(np.linalg.norm(problem.stations_enu_m - target_enu_m, axis=1)))


def run(name, variant, problem):
    try:
        return solve(problem, name, SolveOptions(variant=variant))
    except TooFewMeasurements as error:
        if name not in SCENES:
            pytest.skip(f"{name} needs a measurement mix the generic bearing scene cannot give ({error}); "
                        "add a scene factory to SCENES")
        raise


@pytest.mark.parametrize(("name", "variant"), CASES, ids=IDS)
@pytest.mark.parametrize("local", [False, True], ids=["wgs84", "local"])
def test_noise_free_data_give_the_target(name, variant, local):
    scene = scene_for(name)
    scene = as_local(scene) if local else scene
    problem = scene.problem()
    target = scene.target_enu_m(problem)
    fix = run(name, variant, problem)
    assert np.linalg.norm(fix.position_enu_m - target) < RELATIVE * scale_m(problem, target)
    covariance = fix.covariance_enu_m2
    assert np.all(np.isfinite(covariance)) and np.allclose(covariance, covariance.T)
    assert np.linalg.eigvalsh(covariance)[0] > -1e-9 * np.trace(covariance)
    assert np.trace(covariance) > 0
    assert fix.residuals.shape == (problem.n_measurements,)
    assert np.max(np.abs(fix.normalized_residuals)) < 1e-4


@pytest.mark.parametrize(("name", "variant"), CASES, ids=IDS)
def test_station_and_measurement_order_do_not_matter(name, variant):
    scene = scene_for(name)
    measurements = scene.measurements(np.random.default_rng(11))
    reference = run(name, variant, sc.build(scene, measurements))
    n = len(scene.stations)
    order = np.random.default_rng(3).permutation(len(measurements))
    moved = run(name, variant, sc.build(scene, measurements, station_order=range(n)[::-1], measurement_order=order))
    scale = scale_m(sc.build(scene, measurements), scene.target_enu_m())
    assert np.linalg.norm(moved.position_enu_m - reference.position_enu_m) < RELATIVE * scale
    np.testing.assert_allclose(moved.covariance_enu_m2, reference.covariance_enu_m2,
                               atol=RELATIVE * np.trace(reference.covariance_enu_m2))
    if reference.estimated_bearing_errors_rad is not None:
        bearings = [i for i, m in enumerate(measurements) if type(m).__name__ == "Bearing"]
        reordered = [bearings.index(i) for i in order if i in bearings]
        np.testing.assert_allclose(moved.estimated_bearing_errors_rad,
                                   reference.estimated_bearing_errors_rad[reordered], atol=1e-9)


@pytest.mark.parametrize(("name", "variant"), CASES, ids=IDS)
@pytest.mark.parametrize("frame", ["wgs84", "local"])
def test_moving_the_scene_500_km_does_not_matter(name, variant, frame):
    scene = scene_for(name)
    if frame == "wgs84":
        moved_scene = sc.shifted(scene, SHIFT_LON_DEG)
    else:
        scene = as_local(scene)
        moved_scene = sc.translated(scene, 500e3, -200e3)
    measurements = scene.measurements(np.random.default_rng(5))
    problem = sc.build(scene, measurements)
    moved_problem = sc.build(moved_scene, measurements)
    reference = run(name, variant, problem)
    moved = run(name, variant, moved_problem)
    offset = moved_problem.stations_enu_m[0] - problem.stations_enu_m[0]
    scale = scale_m(problem, scene.target_enu_m(problem))
    assert np.linalg.norm(moved.position_enu_m - offset - reference.position_enu_m) < RELATIVE * scale
    np.testing.assert_allclose(moved.covariance_enu_m2, reference.covariance_enu_m2,
                               atol=1e-5 * np.trace(reference.covariance_enu_m2))


@pytest.mark.parametrize(("name", "variant"), CASES, ids=IDS)
def test_one_line_of_sight_without_range_gives_no_fix(name, variant):
    scene = scene_for(name)
    first = scene.sensors[0]
    single = sc.Scene("one line of sight", scene.stations[:1],
                      (sc.Sensor(first.station_id, first.sigma_azimuth_rad, first.sigma_elevation_rad),),
                      scene.target, scene.altitude_m)
    with pytest.raises((TooFewMeasurements, UnobservableGeometry)):
        solve(single.problem(), name, SolveOptions(variant=variant))


def _azimuth_only_paper_000():
    scene = sc.paper_000()
    sensors = tuple(sc.Sensor(s.station_id, s.sigma_azimuth_rad) for s in scene.sensors)
    return sc.Scene("paper 000 azimuth-only", scene.stations, sensors, scene.target, scene.target.alt_m)


def _generic_without_altitude():
    scene = sc.generic_azimuth_only()
    return sc.Scene(scene.name, scene.stations, scene.sensors, scene.target, None)


def _unknown_sigma_two_bearings():
    scene = sc.generic_azimuth_only(sigma_known=False)
    return sc.Scene(scene.name, scene.stations[:2], scene.sensors[:2], scene.target, scene.altitude_m, False)


#: Each method's documented failures: scene, variant, error, words the message must contain.
FAILURES = [
    ("ove", sc.paper_000, None, TooFewMeasurements, ["at least 3 lines of sight", "got 2"]),
    ("ple3d", sc.paper_000, None, UnobservableGeometry, ["collinear horizontal geometry", "ground track"]),
    ("ws3d", sc.paper_000, None, UnobservableGeometry, ["collinear horizontal geometry", "ground track"]),
    ("ple3d", lambda: sc.paper_000(looks=2), None, UnobservableGeometry, ["collinear"]),
    ("tls", _azimuth_only_paper_000, None, UnobservableGeometry, ["collinear horizontal geometry"]),
    ("ctls", _azimuth_only_paper_000, "newton", UnobservableGeometry, ["collinear horizontal geometry"]),
    ("ctls", _azimuth_only_paper_000, "projected", UnobservableGeometry, ["collinear horizontal geometry"]),
    ("taylor_wls", _azimuth_only_paper_000, None, UnobservableGeometry, ["do not determine"]),
    ("taylor_wls", _generic_without_altitude, None, TooFewMeasurements, ["altitude", "elevations"]),
    ("tls", _generic_without_altitude, None, TooFewMeasurements, ["altitude"]),
    ("ctls", _generic_without_altitude, None, TooFewMeasurements, ["altitude"]),
    ("taylor_wls", _unknown_sigma_two_bearings, None, TooFewMeasurements, ["N - 2", "more than 2 bearings"]),
    ("ctls", sc.generic_azimuth_only, "cubic", InvalidInput, ["newton", "projected"]),
]


@pytest.mark.parametrize(("name", "factory", "variant", "error", "words"), FAILURES,
                         ids=[f"{f[0]}-{f[3].__name__}-{i}" for i, f in enumerate(FAILURES)])
def test_documented_failures(name, factory, variant, error, words):
    with pytest.raises(error) as raised:
        solve(factory().problem(), name, SolveOptions(variant=variant))
    for word in words:
        assert word in raised.value.message
    assert isinstance(raised.value, LocalizationError)
