"""deploy/compose.yaml and deploy/kubernetes/ against the app, its settings and the Dockerfile.

Drift caught here: a probe path that is not a route, an environment variable that no setting reads (a
renamed setting leaves the manifests configuring nothing), an image tag or port that is not the one the
Dockerfile and the package give, a pod that could run as root or write its root filesystem.
"""

from __future__ import annotations

import importlib.metadata
import pathlib
import re

import pytest
import yaml

from service.app import create_app
from service.renderings.tak import TakSettings
from service.settings import Settings

ROOT = pathlib.Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
IMAGE = f"passive-locator:{importlib.metadata.version('passive-locator')}"


def _documents(path: pathlib.Path) -> list[dict]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d]


@pytest.fixture(scope="module")
def k8s() -> dict:
    found = {}
    for path in sorted(p for p in (DEPLOY / "kubernetes").glob("*.yaml") if p.name != "kustomization.yaml"):
        for document in _documents(path):
            found[(document["kind"], document["metadata"]["name"])] = document
    return found


@pytest.fixture(scope="module")
def compose() -> dict:
    return _documents(DEPLOY / "compose.yaml")[0]


@pytest.fixture(scope="module")
def routes() -> set[str]:
    return set(create_app(Settings(store="sqlite:///:memory:")).openapi()["paths"])


def _dockerfile() -> dict:
    text = (ROOT / "Dockerfile").read_text()
    runtime = text.split("\nFROM ")[-1]
    return {"expose": int(re.search(r"^EXPOSE (\d+)", runtime, re.M).group(1)),
            "user": re.search(r"^USER (\d+):(\d+)", runtime, re.M).groups(),
            "cmd_port": int(re.search(r'"--port", "(\d+)"', runtime).group(1))}


#: Environment variables that are not service settings but are read by the service all the same.
OTHER_ENV = {"PROMETHEUS_MULTIPROC_DIR"}


def _known_env() -> set[str]:
    names = set(OTHER_ENV)
    for model in (Settings, TakSettings):
        prefix = model.model_config["env_prefix"]
        names |= {f"{prefix}{field}".upper() for field in model.model_fields}
    return names


def _container(k8s) -> dict:
    return k8s[("Deployment", "passive-locator")]["spec"]["template"]["spec"]["containers"][0]


def test_kustomization_lists_every_manifest():
    kustomization = yaml.safe_load((DEPLOY / "kubernetes" / "kustomization.yaml").read_text())
    listed = set(kustomization["resources"])
    present = {p.name for p in (DEPLOY / "kubernetes").glob("*.yaml")} - {"kustomization.yaml"}
    assert listed == present


def test_probes_are_routes_and_the_pod_is_locked_down(k8s, routes):
    container = _container(k8s)
    assert container["livenessProbe"]["httpGet"]["path"] == "/healthz"
    assert container["readinessProbe"]["httpGet"]["path"] == "/readyz"
    for probe in ("livenessProbe", "readinessProbe", "startupProbe"):
        assert container[probe]["httpGet"]["path"] in routes
    pod = k8s[("Deployment", "passive-locator")]["spec"]["template"]["spec"]
    uid, gid = _dockerfile()["user"]
    assert pod["securityContext"]["runAsNonRoot"] is True
    assert (str(pod["securityContext"]["runAsUser"]), str(pod["securityContext"]["runAsGroup"])) == (uid, gid)
    assert container["securityContext"]["readOnlyRootFilesystem"] is True
    assert container["securityContext"]["allowPrivilegeEscalation"] is False
    assert {"cpu", "memory"} <= set(container["resources"]["requests"]) and container["resources"]["limits"]
    assert any(m["mountPath"] == "/tmp" for m in container["volumeMounts"])  # multiprocess metrics, tempfiles


def test_image_and_port_agree_with_the_dockerfile(k8s, compose):
    docker = _dockerfile()
    assert docker["expose"] == docker["cmd_port"]
    container = _container(k8s)
    assert container["image"] == IMAGE == compose["services"]["api"]["image"]
    assert [p["containerPort"] for p in container["ports"]] == [docker["expose"]]
    assert container["args"][container["args"].index("--port") + 1] == str(docker["expose"])
    service = k8s[("Service", "passive-locator")]
    assert service["spec"]["ports"][0]["targetPort"] == container["ports"][0]["name"]
    assert all(p.endswith(f":{docker['expose']}") for p in compose["services"]["api"]["ports"])
    assert f"127.0.0.1:{docker['expose']}/readyz" in " ".join(compose["services"]["api"]["healthcheck"]["test"])


def test_every_environment_variable_is_a_setting(k8s, compose):
    known = _known_env()
    container = _container(k8s)
    used = {e["name"] for e in container["env"]} | set(compose["services"]["api"]["environment"])
    commented = set(re.findall(r"#\s*(PASSIVE_LOCATOR_[A-Z_]+):", (DEPLOY / "compose.yaml").read_text()))
    assert used | commented <= known, sorted((used | commented) - known)
    for entry in container["env"]:
        ref = entry.get("valueFrom", {}).get("secretKeyRef")
        if ref:
            assert ref["key"] in k8s[("Secret", ref["name"])]["stringData"]
    assert compose["services"]["api"]["environment"]["PASSIVE_LOCATOR_STORE"].startswith("redis://redis:")
    store = next(e["value"] for e in container["env"] if e["name"] == "PASSIVE_LOCATOR_STORE")
    assert store.startswith("redis://passive-locator-redis:") and ("Service", "passive-locator-redis") in k8s


def test_redis_persists_with_aof_and_everything_has_a_healthcheck(k8s, compose):
    redis_args = k8s[("StatefulSet", "passive-locator-redis")]["spec"]["template"]["spec"]["containers"][0]["args"]
    for args in (redis_args, compose["services"]["redis"]["command"]):
        assert args[args.index("--appendonly") + 1] == "yes"
    assert compose["services"]["api"]["deploy"]["replicas"] == 2
    assert all("healthcheck" in service for service in compose["services"].values())
    assert compose["services"]["api"]["depends_on"]["redis"]["condition"] == "service_healthy"
    assert compose["services"]["api"]["read_only"] is True
    hpa = k8s[("HorizontalPodAutoscaler", "passive-locator")]
    assert hpa["spec"]["scaleTargetRef"]["name"] == "passive-locator"
    assert hpa["spec"]["minReplicas"] >= 2


def test_dask_scheduler_and_workers_agree_with_each_other_and_the_package(k8s, compose):
    """The workers dial the scheduler's own service and port; both run the image with the `distributed`
    extra that pyproject.toml defines; the API's setting names that scheduler."""
    import tomllib

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    dask_image = IMAGE.replace("passive-locator:", "passive-locator-dask:")
    scheduler = compose["services"]["dask-scheduler"]
    worker = compose["services"]["dask-worker"]
    assert scheduler["build"]["args"]["EXTRAS"] in extras
    assert any(r.startswith("dask[distributed]") for r in extras[scheduler["build"]["args"]["EXTRAS"]])
    assert scheduler["image"] == worker["image"] == dask_image
    port = scheduler["command"][scheduler["command"].index("--port") + 1]
    assert f"tcp://dask-scheduler:{port}" in worker["command"]
    assert worker["deploy"]["replicas"] == 2
    assert f"PASSIVE_LOCATOR_DASK_SCHEDULER: tcp://dask-scheduler:{port}" in (DEPLOY / "compose.yaml").read_text()

    service = k8s[("Service", "passive-locator-dask-scheduler")]
    comm = next(p for p in service["spec"]["ports"] if p["name"] == "tcp-comm")
    k8s_scheduler = k8s[("Deployment", "passive-locator-dask-scheduler")]["spec"]["template"]["spec"]
    k8s_worker = k8s[("Deployment", "passive-locator-dask-worker")]["spec"]
    assert str(comm["port"]) == k8s_scheduler["containers"][0]["args"][
        k8s_scheduler["containers"][0]["args"].index("--port") + 1]
    assert f"tcp://passive-locator-dask-scheduler:{comm['port']}" in k8s_worker["template"]["spec"]["containers"][0]["args"]
    assert k8s_worker["replicas"] == 2
    for pod in (k8s_scheduler, k8s_worker["template"]["spec"]):
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert pod["containers"][0]["image"] == dask_image
        assert pod["containers"][0]["securityContext"]["readOnlyRootFilesystem"] is True


def _numba_cache_dir() -> str:
    """The image's numba cache: where the build fills it, the runtime stage copies it and the runtime reads it."""
    text = (ROOT / "Dockerfile").read_text()
    build, runtime = text.split("\nFROM ")[-2:]
    built = re.search(r"NUMBA_CACHE_DIR=(\S+)", build).group(1)
    used = re.search(r"^ENV .*NUMBA_CACHE_DIR=(\S+)", runtime, re.M).group(1)
    assert built == used, (built, used)
    assert re.search(rf"^COPY --from=build (--chown=\S+ )?{re.escape(built)} {re.escape(used)}$", runtime, re.M)
    return used


def _hides(mount_path: str, directory: str) -> bool:
    mount = mount_path.rstrip("/") or "/"
    return directory == mount or directory.startswith(mount.rstrip("/") + "/")


def _image_pods(k8s) -> list[dict]:
    image = IMAGE.split(":")[0]
    return [d["spec"]["template"]["spec"] for (kind, _), d in k8s.items() if kind in ("Deployment", "StatefulSet")
            and any(c["image"].split(":")[0] in (image, image + "-dask") for c in d["spec"]["template"]["spec"]
                    ["containers"])]


def test_no_volume_hides_the_images_kernel_cache(k8s, compose):
    """A volume over the image's numba cache (a fresh /tmp once hid it) makes every start compile its kernels."""
    cache = _numba_cache_dir()
    assert not _hides("/tmp", cache), "the cache is under /tmp, which every manifest mounts a volume over"
    pods = _image_pods(k8s)
    assert len(pods) == 3  # the API, the Dask scheduler and its workers
    for pod in pods:
        for container in pod["containers"]:
            for mount in container.get("volumeMounts", []):
                assert not _hides(mount["mountPath"], cache), (container["name"], mount)
            assert "NUMBA_CACHE_DIR" not in {e["name"] for e in container.get("env", [])}
    for name, service in compose["services"].items():
        if not service["image"].startswith(IMAGE.split(":")[0]):
            continue
        paths = [t.split(":")[0] for t in service.get("tmpfs", [])]
        paths += [v.split(":")[1] if isinstance(v, str) else v["target"] for v in service.get("volumes", [])]
        assert not any(_hides(p, cache) for p in paths), (name, paths)
        assert "NUMBA_CACHE_DIR" not in service.get("environment", {})


def test_kernel_cache_hider_is_caught():
    """The check above fails a mount over the cache or over a directory above it."""
    cache = _numba_cache_dir()
    assert _hides(cache, cache) and _hides("/opt", cache) and _hides("/", cache)
    assert not _hides("/tmp", cache) and not _hides(cache + "-other", cache)


def test_start_budgets_cover_a_start_that_compiles(k8s, compose):
    """Every probe and healthcheck allows a start that compiles the kernels (the README's measured figure)."""
    from service.ops.kernel_cache import COLD_START_S

    worst = COLD_START_S[1]
    probe = _container(k8s)["startupProbe"]
    assert probe["periodSeconds"] * probe["failureThreshold"] >= 2 * worst
    start_period = compose["services"]["api"]["healthcheck"]["start_period"]
    assert int(start_period.removesuffix("s")) >= 2 * worst
    docker = re.search(r"^HEALTHCHECK .*--start-period=(\d+)s", (ROOT / "Dockerfile").read_text(), re.M)
    assert int(docker.group(1)) >= 2 * worst


def test_dask_workers_load_the_images_kernels(k8s, compose):
    worker = k8s[("Deployment", "passive-locator-dask-worker")]["spec"]["template"]["spec"]["containers"][0]
    for args in (worker["args"], compose["services"]["dask-worker"]["command"]):
        assert args[args.index("--preload") + 1] == "service.ops.kernel_cache"
