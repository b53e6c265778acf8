"""The deployment files: docker-compose.yml (replicas behind a proxy with session affinity, Redis, the
trainer), the Dockerfile targets it names, the nginx config it mounts, and scripts/redis.sh."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import redis
import yaml

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    return data


def _emulators(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The emulator replicas: the emulator image run with its own command (the controller API shares the image)."""
    return {
        name: svc
        for name, svc in compose["services"].items()
        if svc.get("build", {}).get("target") == "emulator" and "command" not in svc
    }


def _stages(dockerfile: Path) -> dict[str, str]:
    """Stage name -> its text, from ``FROM ... AS name`` lines."""
    text = dockerfile.read_text()
    parts = re.split(r"(?im)^FROM\s+\S+\s+AS\s+(\S+)\s*$", text)
    return {parts[i].lower(): parts[i + 1] for i in range(1, len(parts), 2)}


def test_services(compose: dict[str, Any]) -> None:
    services = compose["services"]
    assert {"redis", "proxy", "trainer"} <= set(services)
    assert len(_emulators(compose)) >= 2
    assert services["trainer"]["profiles"] == ["train"]  # one-shot, not started by `up`
    assert services["trainer"]["command"][0] == "train"
    assert "web" in services and "web" in services["proxy"]["depends_on"]


def test_web_service_matches_its_settings(compose: dict[str, Any]) -> None:
    from services.web.settings import Settings

    web = compose["services"]["web"]
    env = web["environment"]
    known = {name.upper() for name in Settings.model_fields}
    assert set(env) <= known, set(env) - known  # every variable is a setting of services.web
    assert env["PORT"] == "8080" and env["HOST"] == "0.0.0.0"
    assert env["EMULATOR_URL"] == "/api/emulator" and env["CONTROLLER_URL"] == "/api/controller"
    assert any(v.split(":")[1] == env["ARTIFACTS_DIR"] for v in web["volumes"])
    assert any(p.split(":")[-1] == "8080" for p in compose["services"]["proxy"]["ports"])


def test_proxy_serves_the_dashboard_and_the_apis(compose: dict[str, Any]) -> None:
    conf = (ROOT / "deploy" / "nginx" / "emulator.conf").read_text()
    block = conf.split("listen 8080;")[1]
    assert "proxy_pass http://web:8080;" in block
    assert "location /api/emulator/" in block and "proxy_pass http://$emulator_upstream;" in block
    assert "rewrite ^/api/emulator(/.*)$ $1 break;" in block  # the map then sees the emulator's own path
    assert "location /api/controller/" in block and "proxy_buffering off;" in block  # server-sent events


def test_controller_services_match_their_settings(compose: dict[str, Any]) -> None:
    from services.controller.settings import Settings

    known = {name.upper() for name in Settings.model_fields}
    services = compose["services"]
    api, worker = services["controller-api"], services["controller-worker"]
    for name, svc in (("controller-api", api), ("controller-worker", worker)):
        env = svc["environment"]
        assert set(env) <= known, (name, set(env) - known)  # every variable is a controller setting
        assert env["REDIS_URL"].startswith("redis://redis:"), name
        assert "redis" in svc["depends_on"], name
        assert any(v.split(":")[1] == env["ARTIFACTS_DIR"] for v in svc["volumes"]), name
    assert api["build"]["target"] == "emulator"  # the API needs no PyTorch
    assert api["command"] == ["python", "-m", "services.controller"]
    assert api["environment"]["PORT"] == str(Settings.model_fields["port"].default)
    assert "8001" in api["healthcheck"]["test"][-1]
    assert worker["build"]["target"] == "trainer" and worker["command"] == ["worker"]  # `neuro worker`
    conf = (ROOT / "deploy" / "nginx" / "emulator.conf").read_text()
    assert f"controller-api:{api['environment']['PORT']}" in conf  # the proxy reaches the API


def test_trainer_services_match_their_settings(compose: dict[str, Any]) -> None:
    from services.trainer.settings import Settings

    known = {name.upper() for name in Settings.model_fields}
    services = compose["services"]
    api, worker = services["trainer-api"], services["trainer-worker"]
    for name, svc in (("trainer-api", api), ("trainer-worker", worker)):
        env = svc["environment"]
        assert set(env) <= known, (name, set(env) - known)  # every variable is a trainer setting
        assert env["REDIS_URL"].startswith("redis://redis:"), name
        assert "redis" in svc["depends_on"], name
        # both write the data directory (uploads, claimed names, exported emulators), never the defaults
        assert f"data:{env['DATA_DIR']}" in svc["volumes"], name
        assert f"./artifacts:{env['ARTIFACTS_DIR']}:ro" in svc["volumes"], name
    assert api["build"]["target"] == "emulator"  # the API needs no PyTorch
    assert api["command"] == ["python", "-m", "services.trainer"]
    assert api["environment"]["PORT"] == str(Settings.model_fields["port"].default)
    assert "8002" in api["healthcheck"]["test"][-1]
    assert worker["build"]["target"] == "trainer"
    assert worker["entrypoint"] == ["python", "-m", "services.trainer.worker"]
    assert float(worker["cpus"]) <= 1.0 and int(worker["environment"]["WORKER_NICE"]) > 0  # serving first
    assert compose["services"]["web"]["environment"]["TRAINER_URL"] == "/api/trainer"
    conf = (ROOT / "deploy" / "nginx" / "emulator.conf").read_text()
    assert f"trainer-api:{api['environment']['PORT']}" in conf and "location /api/trainer/" in conf


def test_the_trainer_api_imports_no_torch() -> None:
    """The trainer API runs from the emulator image (no PyTorch): it checks uploads with MuJoCo alone."""
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('torch', 'tqdm', 'matplotlib', 'onnx'):\n"
        "            raise ImportError(f'{name} is not in the emulator image')\n"
        "sys.meta_path.insert(0, Block())\n"
        "import services.trainer.__main__\n"
        "from services.trainer.app import create_app\n"
        "from services.trainer.settings import Settings\n"
        "create_app(Settings(redis_url='redis://127.0.0.1:1/0'))\n"
    )
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=60)


def test_replicas_have_distinct_ids_and_use_redis(compose: dict[str, Any]) -> None:
    ids = []
    for name, svc in _emulators(compose).items():
        env = svc["environment"]
        ids.append(env["REPLICA_ID"])
        assert re.fullmatch(r"[A-Za-z0-9_]+", env["REPLICA_ID"]), name
        assert env["REDIS_URL"].startswith("redis://redis:"), name
        assert "redis" in svc["depends_on"], name
        assert env["ARTIFACTS_DIR"] == "/artifacts"
        assert any(v.split(":")[1] == "/artifacts" for v in svc["volumes"])
    assert len(set(ids)) == len(ids)


def test_users_data_is_a_volume_that_only_the_trainer_writes(compose: dict[str, Any]) -> None:
    """Uploads and trainings live in a volume of their own; the committed defaults are mounted read-only
    everywhere, and only the trainer's API and workers (and the one-shot ``neuro train``) write data."""
    assert "data" in compose["volumes"]
    writers = {"trainer-api", "trainer-worker", "trainer"}
    for name, svc in compose["services"].items():
        mounts = svc.get("volumes", [])
        for m in mounts:
            if m.startswith("./artifacts:"):
                assert m.endswith(":ro"), (name, m)
            if m.startswith("data:"):
                assert m.endswith(":ro") != (name in writers), (name, m)
        env = svc.get("environment", {})
        if "ARTIFACTS_DIR" in env:  # a service that reads the defaults reads the users' models too
            assert any(m == f"data:{env['DATA_DIR']}" or m == f"data:{env['DATA_DIR']}:ro" for m in mounts), (
                name
            )


def test_dockerfile_targets(compose: dict[str, Any]) -> None:
    for svc in compose["services"].values():
        build = svc.get("build")
        if build is None:
            continue
        dockerfile = ROOT / build.get("context", ".") / build.get("dockerfile", "Dockerfile")
        assert dockerfile.is_file()
        assert build["target"] in _stages(dockerfile)
    stages = _stages(ROOT / "Dockerfile")
    assert "python:3.11-slim" in (ROOT / "Dockerfile").read_text()
    emulator = stages["emulator"]
    assert "torch==" not in emulator and "install torch" not in emulator  # the emulator image has no PyTorch
    # the emulator's requirements, as its RUN line derives them from pyproject.toml
    code = re.search(r'python -c "(.*?)"\s*\\?\s*> /tmp/requirements.txt', emulator.replace("\\\n", ""), re.S)
    assert code is not None
    reqs = subprocess.run(
        [sys.executable, "-c", code.group(1)], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    names = {r.split("==")[0].split("[")[0] for r in reqs}
    assert {"onnxruntime", "fastapi", "redis", "mujoco", "numpy"} <= names and "torch" not in names
    assert all("==" in r for r in reqs)  # pinned
    assert "torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu" in stages["trainer"]


# Installed in the full environment but not in the dashboard's image (it installs fastapi, uvicorn, pydantic
# and pydantic-settings only, and copies neuroanimator's sources for the artifact registry's readers).
NOT_IN_WEB_IMAGE = (
    "numpy",
    "torch",
    "onnxruntime",
    "mujoco",
    "redis",
    "rq",
    "prometheus_client",
)


def test_web_image_holds_what_the_web_service_imports(tmp_path: Path) -> None:
    """The dashboard's image copies a few folders of services/ and neuroanimator/: the static server, which
    reads evaluation and benchmark results through the artifact registry, starts from them alone."""
    stage = _stages(ROOT / "deploy" / "web" / "Dockerfile")["web"]
    copied = re.findall(r"(?m)^COPY ((?:services|neuroanimator)\S*) \./\1$", stage)
    assert "neuroanimator" in copied, copied
    assert "services/web" in copied, copied
    app = tmp_path / "app"
    for path in copied:
        src, dst = ROOT / path, app / path
        if src.is_dir():
            shutil.copytree(src, dst, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src, dst)
    code = (
        "import sys\n"
        f"blocked = {NOT_IN_WEB_IMAGE!r}\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in blocked:\n"
        "            raise ImportError(f'{name} is not in the web image')\n"
        "sys.meta_path.insert(0, Block())\n"
        "import services.web.__main__\n"
        "from services.web.app import create_app\n"
        "from services.web.settings import Settings\n"
        f"app = create_app(Settings(web_dist={str(tmp_path / 'dist')!r}, artifacts_dir={str(ROOT / 'artifacts')!r}))\n"
        "from fastapi.testclient import TestClient\n"
        "assert TestClient(app).get('/artifacts/lander/eval.json').status_code == 200\n"
        f"assert services.web.__file__.startswith({str(app)!r}), services.web.__file__\n"
    )
    env = {**os.environ, "PYTHONPATH": str(app)}
    subprocess.run([sys.executable, "-c", code], cwd=app, env=env, check=True, timeout=60)


def test_proxy_routes_by_replica_prefix(compose: dict[str, Any]) -> None:
    proxy = compose["services"]["proxy"]
    mounts = [v.split(":") for v in proxy["volumes"]]
    conf_paths = [ROOT / host for host, target, *_ in mounts if target.startswith("/etc/nginx/")]
    assert len(conf_paths) == 1 and conf_paths[0].is_file()
    conf = conf_paths[0].read_text()
    upstreams = {
        name: re.findall(r"server\s+([^;\s]+);", body)
        for name, body in re.findall(r"upstream\s+(\S+)\s*\{([^}]*)\}", conf)
    }
    routes = dict(re.findall(r"~\^/\(\?:ws/\)\?sessions/([A-Za-z0-9_]+)-\s+(\S+);", conf))
    emulators = _emulators(compose)
    for name, svc in emulators.items():
        rid = svc["environment"]["REPLICA_ID"]
        assert routes[rid] in upstreams, rid  # /sessions/<rid>-... and /ws/sessions/<rid>-...
        assert upstreams[routes[rid]] == [f"{name}:8000"], rid  # ... reach that replica only
        assert set(proxy["depends_on"]) >= {name}
    assert "proxy_pass http://$emulator_upstream;" in conf
    assert "Upgrade $http_upgrade" in conf  # websockets pass through
    any_upstream = re.search(r"default\s+(\S+);", conf.split("map $http_upgrade")[0])
    assert any_upstream and set(upstreams[any_upstream.group(1)]) == {f"{n}:8000" for n in emulators}


def _has_compose() -> bool:
    if shutil.which("docker") is None:
        return False
    r = subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=20, check=False)
    return r.returncode == 0


def test_docker_compose_config() -> None:
    if not _has_compose():
        pytest.skip("no docker CLI with the compose plugin here; the YAML checks above still ran")
    subprocess.run(["docker", "compose", "-f", str(ROOT / "docker-compose.yml"), "config", "-q"], check=True)


def test_redis_script_starts_a_server(tmp_path: Path) -> None:
    if shutil.which("redis-server") is None:
        pytest.skip("no redis-server binary to start")
    pidfile = tmp_path / "redis.pid"
    env = {k: v for k, v in os.environ.items() if k != "REDIS_URL"}
    env["REDIS_PROBE"] = "127.0.0.1:1"  # nothing there: the script must start its own
    r = subprocess.run(
        [str(ROOT / "scripts" / "redis.sh"), "--pidfile", str(pidfile)],
        capture_output=True,
        text=True,
        env=env,
        timeout=30,
        check=True,
    )
    url = r.stdout.strip()
    assert re.fullmatch(r"redis://127\.0\.0\.1:\d+/0", url), r.stdout
    try:
        client = redis.Redis.from_url(url)
        assert client.ping()
        client.close()
    finally:
        os.kill(int(pidfile.read_text()), signal.SIGTERM)
    env["REDIS_URL"] = "redis://example:6379/3"
    r = subprocess.run(
        [str(ROOT / "scripts" / "redis.sh")], capture_output=True, text=True, env=env, check=True
    )
    assert r.stdout.strip() == "redis://example:6379/3"


def test_compose_redis_keeps_its_data_and_its_command_runs(compose: dict[str, Any], tmp_path: Path) -> None:
    """AOF on (fsync every second) into a volume, so the queue, job records and checkpoints survive a
    restart of Redis (docs/persistence.md); the command's options are ones this redis-server takes."""
    svc = compose["services"]["redis"]
    cmd = svc["command"]
    assert cmd[0] == "redis-server"
    opts = dict(zip(cmd[1::2], cmd[2::2], strict=True))
    assert opts["--appendonly"] == "yes" and opts["--appendfsync"] == "everysec"
    assert any(str(v).endswith(":/data") for v in svc["volumes"])
    for name, s in compose["services"].items():
        env = s.get("environment") or {}
        if "API_KEYS" in env and name != "web":  # the dashboard's server reads only whether keys are on
            assert "API_KEY_SECRET" in env, name  # the key ids' secret goes with the keys
    if shutil.which("redis-server") is None:
        pytest.skip("redis-server is not installed")
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    proc = subprocess.Popen(
        [*cmd, "--port", str(port), "--bind", "127.0.0.1", "--dir", str(tmp_path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        client = redis.Redis(port=port, socket_connect_timeout=0.2)
        deadline = time.monotonic() + 10
        while True:
            try:
                client.ping()
                break
            except redis.RedisError:
                assert time.monotonic() < deadline, "redis-server did not start with compose's options"
                time.sleep(0.05)
        assert client.config_get("appendonly") == {"appendonly": "yes"}
        assert client.config_get("appendfsync") == {"appendfsync": "everysec"}
        client.close()
    finally:
        proc.terminate()
        proc.wait(10)
