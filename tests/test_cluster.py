"""The Kubernetes deployment (deploy/, docs/cluster.md), checked without a cluster: every configuration
file against Dagster's and dagster-k8s's own schemas, the pod a GPU step gets built the way the
k8s_job_executor builds it, and the multiprocess executor (steps in their own processes, as pods are)
materialising the same data as an in-process run.

Needs the optional `cluster` extra (dagster-k8s); without it every test here FAILS, saying how to
install it (bash scripts/bootstrap.sh test installs it)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import dagster as dg
import numpy as np
import pytest
import xarray as xr
import yaml

from simart_pipeline import cluster, registry

try:
    import dagster_k8s
    from dagster_k8s import K8sRunLauncher
    from dagster_k8s.container_context import K8sContainerContext
    from dagster_k8s.job import DagsterK8sJobConfig, construct_dagster_k8s_job, get_user_defined_k8s_config
except ImportError:  # reported by every test below, never skipped
    dagster_k8s = None

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
TINY = REPO / "tests" / "scenes" / "tiny"
GPU = cluster.GPU_RESOURCE


@pytest.fixture(autouse=True)
def _cluster_extra():
    if dagster_k8s is None:
        pytest.fail(f"dagster-k8s is not installed: {cluster.INSTALL_HINT}", pytrace=False)


def _yaml(path: Path):
    return yaml.safe_load(path.read_text())


@pytest.fixture(scope="module")
def values():
    return _yaml(DEPLOY / "helm" / "values.yaml")


@pytest.fixture(scope="module")
def user_deployment(values):
    (dep,) = values["dagster-user-deployments"]["deployments"]
    return dep


@pytest.fixture(scope="module")
def k8s_defs():
    from simart_pipeline.definitions import build_definitions

    return build_definitions(executor="k8s")


# --- versions ---------------------------------------------------------------------------------------
def test_dagster_k8s_is_the_release_of_the_installed_dagster():
    """dagster-k8s 0.29.N is released with dagster 1.13.N and works with that one only."""
    from importlib.metadata import version

    k8s, core = version("dagster-k8s").split("."), version("dagster").split(".")
    assert (k8s[0], k8s[1], k8s[2]) == ("0", str(int(core[1]) + 16), core[2]), (version("dagster-k8s"), version("dagster"))
    pyproject = (REPO / "pyproject.toml").read_text()
    assert re.search(r'^cluster = \["dagster-k8s>=0\.29,<0\.30"\]', pyproject, re.M)


# --- the Dagster instance: dagster.yaml and what the chart renders from the values -------------------
def _instance_from_values(values: dict, namespace: str = "simart", release: str = "simart") -> dict:
    """The run launcher, run coordinator and concurrency sections of the dagster.yaml the Dagster chart
    renders from ``values`` (its templates helpers/instance/_run-launcher.tpl, _run-coordinator.tpl,
    _concurrency.tpl, configmap-instance.yaml), for the keys these values use."""
    rl = values["runLauncher"]
    assert rl["type"] == "K8sRunLauncher"
    k = rl["config"]["k8sRunLauncher"]
    known = {"loadInclusterConfig", "kubeconfigFile", "jobNamespace", "imagePullPolicy", "envConfigMaps",
             "envSecrets", "envVars", "volumeMounts", "volumes", "labels", "resources", "failPodOnRunFailure",
             "schedulerName", "securityContext", "runK8sConfig"}
    assert set(k) <= known, f"keys the chart's run launcher template does not read: {set(k) - known}"
    launcher = {"load_incluster_config": k.get("loadInclusterConfig", True),
                "job_namespace": k.get("jobNamespace") or namespace,
                "image_pull_policy": k.get("imagePullPolicy", "Always"),
                "service_account_name": f"{release}-dagster",
                "dagster_home": "/opt/dagster/dagster_home",
                "instance_config_map": f"{release}-dagster-instance",
                "postgres_password_secret": "dagster-postgresql-secret"}
    for src, dst in (("envVars", "env_vars"), ("volumeMounts", "volume_mounts"), ("volumes", "volumes"),
                     ("labels", "labels"), ("resources", "resources"), ("securityContext", "security_context")):
        if k.get(src):
            launcher[dst] = k[src]
    for src, dst in (("envConfigMaps", "env_config_maps"), ("envSecrets", "env_secrets")):
        if k.get(src):
            launcher[dst] = [e["name"] for e in k[src] if "name" in e]
    if k.get("failPodOnRunFailure"):
        launcher["fail_pod_on_run_failure"] = True
    if k.get("runK8sConfig"):
        launcher["run_k8s_config"] = {re.sub(r"([A-Z])", lambda m: "_" + m.group(1).lower(), key): v
                                      for key, v in k["runK8sConfig"].items() if v}
    out = {"run_launcher": {"module": "dagster_k8s", "class": "K8sRunLauncher", "config": launcher}}
    daemon = values["dagsterDaemon"]
    rc = daemon["runCoordinator"]
    if daemon["enabled"] and rc["enabled"]:
        assert rc["type"] == "QueuedRunCoordinator"
        q = rc.get("config", {}).get("queuedRunCoordinator", {})
        conf = {}
        for src, dst in (("maxConcurrentRuns", "max_concurrent_runs"), ("dequeueIntervalSeconds", "dequeue_interval_seconds"),
                         ("dequeueUseThreads", "dequeue_use_threads"), ("dequeueNumWorkers", "dequeue_num_workers")):
            if q.get(src) is not None:
                conf[dst] = q[src]
        out["run_coordinator"] = {"module": "dagster.core.run_coordinator", "class": "QueuedRunCoordinator",
                                  **({"config": conf} if conf else {})}
    c = values.get("concurrency", {})
    if c.get("enabled"):
        pools, runs = c.get("pools", {}), c.get("runs", {})
        section = {}
        p = {dst: pools[src] for src, dst in (("defaultLimit", "default_limit"), ("granularity", "granularity"),
                                              ("opGranularityRunBuffer", "op_granularity_run_buffer"))
             if pools.get(src) is not None}
        if p:
            section["pools"] = p
        r = {"max_concurrent_runs": runs["maxConcurrentRuns"]} if runs.get("maxConcurrentRuns") is not None else {}
        if runs.get("tagConcurrencyLimits"):
            r["tag_concurrency_limits"] = runs["tagConcurrencyLimits"]
        if r:
            section["runs"] = r
        out["concurrency"] = section
    out["telemetry"] = {"enabled": values.get("telemetry", {}).get("enabled", True)}
    return out


def _valid(schema, value):
    from dagster._config import process_config

    result = process_config(schema, value)
    assert result.success, [e.message for e in result.errors]
    return result.value


def test_dagster_yaml_is_a_valid_instance_config(tmp_path):
    from dagster._core.instance.config import dagster_instance_config_schema

    local = _yaml(REPO / "dagster.yaml")
    _valid(dagster_instance_config_schema(), local)
    assert local["run_coordinator"]["class"] == "QueuedRunCoordinator"
    # and a Dagster instance starts from it
    shutil.copyfile(REPO / "dagster.yaml", tmp_path / "dagster.yaml")
    with dg.DagsterInstance.from_config(str(tmp_path)) as instance:
        assert type(instance.run_coordinator).__name__ == "QueuedRunCoordinator"
        assert instance.get_concurrency_config().pool_config.default_pool_limit == 1


def test_helm_values_render_a_valid_instance_mirroring_dagster_yaml(values):
    from dagster._core.instance.config import dagster_instance_config_schema
    from dagster._core.run_coordinator import QueuedRunCoordinator

    rendered = _instance_from_values(values)
    _valid(dagster_instance_config_schema(), rendered)
    launcher = _valid(K8sRunLauncher.config_type(), rendered["run_launcher"]["config"])
    assert launcher["load_incluster_config"] is True
    _valid(QueuedRunCoordinator.config_type(), rendered["run_coordinator"].get("config", {}))
    # the same shape as dagster.yaml: queued runs, pools with op granularity (one limit per pool)
    local = _yaml(REPO / "dagster.yaml")
    assert rendered["run_coordinator"]["class"] == local["run_coordinator"]["class"]
    assert rendered["concurrency"]["pools"]["granularity"] == local["concurrency"]["pools"]["granularity"] == "op"
    assert isinstance(rendered["concurrency"]["pools"]["default_limit"], int)
    assert rendered["concurrency"]["runs"]["max_concurrent_runs"] >= rendered["concurrency"]["pools"]["default_limit"]
    # the chart refuses maxConcurrentRuns in both places
    assert "maxConcurrentRuns" not in values["dagsterDaemon"]["runCoordinator"]["config"]["queuedRunCoordinator"]
    assert values["postgresql"]["enabled"] is True and values["telemetry"]["enabled"] is False


def test_a_broken_run_launcher_config_is_refused():
    """The validation above is real: dagster-k8s's schema refuses what it does not know."""
    from dagster._config import process_config

    cfg = _instance_from_values(_yaml(DEPLOY / "helm" / "values.yaml"))["run_launcher"]["config"]
    assert not process_config(K8sRunLauncher.config_type(), {**cfg, "volume_mount": []}).success
    assert not process_config(K8sRunLauncher.config_type(), {**cfg, "env_vars": "SIMART_DATA=/x"}).success


# --- the shared volume ------------------------------------------------------------------------------
def test_the_data_volume_is_a_readwritemany_claim_every_pod_mounts(values, user_deployment):
    import kubernetes

    (pvc,) = [d for d in yaml.safe_load_all((DEPLOY / "k8s" / "data-pvc.yaml").read_text()) if d]
    model = kubernetes.client.ApiClient()._ApiClient__deserialize(pvc, "V1PersistentVolumeClaim")
    assert model.kind == "PersistentVolumeClaim" and model.spec.access_modes == ["ReadWriteMany"]
    assert re.fullmatch(r"\d+(Gi|Ti)", model.spec.resources.requests["storage"])
    name = model.metadata.name
    launcher = values["runLauncher"]["config"]["k8sRunLauncher"]
    for where in (launcher, user_deployment):
        (vol,) = where["volumes"]
        assert vol["persistentVolumeClaim"]["claimName"] == name
        (mount,) = where["volumeMounts"]
        assert mount["name"] == vol["name"]
    mount_path = launcher["volumeMounts"][0]["mountPath"]
    assert user_deployment["volumeMounts"][0]["mountPath"] == mount_path
    # data and scenes on the volume, the same in the code server, the run pods and the step pods
    ud_env = {e["name"]: e["value"] for e in user_deployment["env"]}
    run_env = dict(v.split("=", 1) for v in launcher["envVars"])
    assert ud_env == run_env
    for var in ("SIMART_DATA", "SIMART_SCENES"):
        assert Path(run_env[var]).is_relative_to(mount_path), var
    assert run_env["SIMART_EXECUTOR"] == "k8s"
    assert cluster.parse_node_selector(run_env["SIMART_GPU_NODE_SELECTOR"])
    # and the image's own defaults agree
    dockerfile_env = dict(re.findall(r"(SIMART_\w+)=(\S+)", (DEPLOY / "Dockerfile").read_text()))
    assert {k: dockerfile_env[k] for k in ("SIMART_DATA", "SIMART_SCENES", "SIMART_EXECUTOR")} == \
        {k: run_env[k] for k in ("SIMART_DATA", "SIMART_SCENES", "SIMART_EXECUTOR")}


# --- the image ---------------------------------------------------------------------------------------
def _instructions(dockerfile: Path) -> list[tuple[str, str]]:
    text = re.sub(r"\\\n", " ", dockerfile.read_text())
    return [(m.group(1).upper(), m.group(2).strip()) for m in
            (re.match(r"\s*(\w+)\s+(.*)", line) for line in text.splitlines() if line.strip() and
             not line.lstrip().startswith("#")) if m]


def test_the_dockerfile_builds_the_code_server_image(user_deployment):
    ins = _instructions(DEPLOY / "Dockerfile")
    (base,) = [a for i, a in ins if i == "FROM"]
    assert re.fullmatch(r"python:3\.1[0-3]-slim-(bookworm|trixie)", base), base  # Debian 12/13
    runs = " ".join(a for i, a in ins if i == "RUN")
    assert re.search(r"apt-get install [^&]*\blibllvm19\b", runs)
    assert re.search(r"pip install \"\.\[cluster\]\"", runs)
    assert "simart preflight" in runs
    # what it copies exists and is not excluded from the build context
    ignored = [line.strip() for line in (REPO / ".dockerignore").read_text().splitlines()
               if line.strip() and not line.startswith("#")]
    for _, arg in [x for x in ins if x[0] == "COPY"]:
        for src in arg.split()[:-1]:
            assert (REPO / src).exists(), src
            assert src.rstrip("/") not in ignored, src
    # the entry point is the gRPC code server of the Definitions pyproject names
    (cmd,) = [a for i, a in ins if i == "CMD"]
    cmd = json.loads(cmd)
    module = re.search(r'module_name = "([\w.]+)"', (REPO / "pyproject.toml").read_text()).group(1)
    assert cmd[:3] == ["dagster", "api", "grpc"] and cmd[cmd.index("-m") + 1] == module
    args = user_deployment["dagsterApiGrpcArgs"]
    assert args[args.index("--module-name") + 1] == module
    assert user_deployment["port"] == int(cmd[cmd.index("--port") + 1])


# --- GPU steps ---------------------------------------------------------------------------------------
def test_k8s_mode_tags_exactly_the_gpu_pools_and_changes_nothing_else(k8s_defs):
    from simart_pipeline.definitions import build_definitions, defs

    local = build_definitions(executor="local")
    gpu_ops = set()
    for key in k8s_defs.resolve_asset_graph().get_all_asset_keys():
        a, b = k8s_defs.resolve_assets_def(key), local.resolve_assets_def(key)
        assert a.code_versions_by_key == b.code_versions_by_key  # a cluster never makes data stale
        if not a.is_executable:
            continue
        assert cluster.K8S_CONFIG_TAG not in b.op.tags
        if a.op.pool in cluster.GPU_POOLS:
            gpu_ops.add(a.op.name)
            cfg = get_user_defined_k8s_config(a.op.tags)
            assert cfg.container_config["resources"]["limits"][GPU] == "1"
        else:
            assert cluster.K8S_CONFIG_TAG not in a.op.tags
    assert gpu_ops == {"cirs", "radar_frames", "ckm_layers", "sensor_frames"}
    assert k8s_defs.resolve_job_def("ckm_tiles").executor_def.name == "k8s"
    assert local.resolve_job_def("ckm_tiles").executor_def is not k8s_defs.resolve_job_def("ckm_tiles").executor_def
    # this process has no SIMART_EXECUTOR: the module's Definitions are the local ones
    assert "SIMART_EXECUTOR" not in os.environ
    assert cluster.K8S_CONFIG_TAG not in defs.resolve_assets_def("cirs").op.tags


def test_executor_mode_comes_from_the_environment(monkeypatch):
    monkeypatch.delenv("SIMART_EXECUTOR", raising=False)
    assert cluster.executor_mode() == "local"
    monkeypatch.setenv("SIMART_EXECUTOR", "k8s")
    assert cluster.executor_mode() == "k8s"
    monkeypatch.setenv("SIMART_EXECUTOR", "kubernetes")
    with pytest.raises(ValueError, match="SIMART_EXECUTOR: 'kubernetes' is not one of local, k8s"):
        cluster.executor_mode()
    assert cluster.parse_node_selector("a=b, cloud.google.com/gke-accelerator=nvidia-l4") == \
        {"a": "b", "cloud.google.com/gke-accelerator": "nvidia-l4"}
    with pytest.raises(ValueError, match="not key=value"):
        cluster.parse_node_selector("gpu")


def _launcher(values, tmp_path) -> K8sRunLauncher:
    """A real K8sRunLauncher from the rendered values; only the cluster credentials are a stand-in
    (a kubeconfig naming an unreachable server: nothing is contacted)."""
    kubeconfig = tmp_path / "kubeconfig"
    kubeconfig.write_text(yaml.safe_dump({
        "apiVersion": "v1", "kind": "Config", "current-context": "none",
        "clusters": [{"name": "none", "cluster": {"server": "https://127.0.0.1:1"}}],
        "contexts": [{"name": "none", "context": {"cluster": "none", "user": "none"}}],
        "users": [{"name": "none", "user": {"token": "none"}}]}))
    cfg = _valid(K8sRunLauncher.config_type(), _instance_from_values(values)["run_launcher"]["config"])
    return K8sRunLauncher(**{**cfg, "load_incluster_config": False, "kubeconfig_file": str(kubeconfig)})


def _step_pod(k8s_defs, values, user_deployment, tmp_path, job_name: str, step_key: str):
    """The Kubernetes Job the k8s_job_executor creates for ``step_key``, merged as its step handler
    does (K8sStepHandler._get_container_context, launch_step): the run launcher's configuration, the
    code location's container context (the chart's includeConfigInLaunchedRuns), the step's tags."""
    from dagster._core.execution.api import create_execution_plan

    launcher = _launcher(values, tmp_path)
    context = K8sContainerContext(
        image_pull_policy=launcher.image_pull_policy, service_account_name=launcher.service_account_name,
        env_vars=launcher.env_vars, volume_mounts=launcher.volume_mounts, volumes=launcher.volumes,
        namespace=launcher.job_namespace, resources=launcher.resources)
    code_location = K8sContainerContext.create_from_config({"k8s": {
        "env": user_deployment["env"], "volumes": user_deployment["volumes"],
        "volume_mounts": user_deployment["volumeMounts"]}})
    context = context.merge(code_location)
    plan = create_execution_plan(k8s_defs.resolve_job_def(job_name))
    tags = plan.get_step_by_key(step_key).tags
    context = context.merge(K8sContainerContext(run_k8s_config=get_user_defined_k8s_config(tags)))
    image = f"{user_deployment['image']['repository']}:{user_deployment['image']['tag']}"
    job = construct_dagster_k8s_job(
        job_config=context.get_k8s_job_config(image, launcher), args=["dagster", "api", "execute_step"],
        job_name=f"dagster-step-{step_key}", user_defined_k8s_config=context.run_k8s_config,
        component="step_worker")
    return job.spec.template.spec


def test_a_ray_tracing_step_pod_gets_a_gpu_a_gpu_node_and_the_data_volume(k8s_defs, values, user_deployment, tmp_path):
    pod = _step_pod(k8s_defs, values, user_deployment, tmp_path, "ckm_tiles", "ckm_layers")
    (container,) = pod.containers
    res = container.resources
    assert res.limits[GPU] == "1" and res.requests[GPU] == "1"
    # the run launcher's requests are kept beside the GPU
    launcher_res = values["runLauncher"]["config"]["k8sRunLauncher"]["resources"]
    assert res.requests["memory"] == launcher_res["requests"]["memory"]
    assert res.limits["memory"] == launcher_res["limits"]["memory"]
    assert pod.node_selector == cluster.parse_node_selector(
        dict(v.split("=", 1) for v in values["runLauncher"]["config"]["k8sRunLauncher"]["envVars"])
        ["SIMART_GPU_NODE_SELECTOR"]) == {"nvidia.com/gpu.present": "true"}
    assert [(t.key, t.operator, t.effect) for t in pod.tolerations] == [(GPU, "Exists", "NoSchedule")]
    # one volume (the launcher's and the code location's are the same one), mounted once
    assert [(v.name, v.persistent_volume_claim.claim_name) for v in pod.volumes] == [("simart-data", "simart-data")]
    assert [(m.name, m.mount_path) for m in container.volume_mounts] == [("simart-data", "/simart")]
    names = [e.name for e in container.env]
    assert len(names) == len(set(names))  # the launcher's and the code location's variables merge, once each
    env = {e.name: e.value for e in container.env}
    assert env["SIMART_DATA"] == "/simart/data" and env["SIMART_EXECUTOR"] == "k8s"
    assert container.image == "registry.example.com/simart-pipeline:0.1.0"


def test_the_rendering_step_gets_a_gpu_and_a_cpu_step_gets_none(k8s_defs, values, user_deployment, tmp_path):
    render = _step_pod(k8s_defs, values, user_deployment, tmp_path, "__ASSET_JOB", "sensor_frames")
    assert render.containers[0].resources.limits[GPU] == "1"
    assert render.node_selector == {"nvidia.com/gpu.present": "true"}
    for step in ("osm_extract", "paired_meshes"):
        cpu = _step_pod(k8s_defs, values, user_deployment, tmp_path, "scene_assets", step)
        assert GPU not in (cpu.containers[0].resources.limits or {}) and GPU not in cpu.containers[0].resources.requests
        assert not cpu.node_selector and not cpu.tolerations
        assert [v.name for v in cpu.volumes] == ["simart-data"]  # every pod sees the data


def test_k8s_executor_run_config_is_validated_by_dagster(k8s_defs):
    job = k8s_defs.resolve_job_def("ckm_tiles")
    ok = dg.validate_run_config(job, {"execution": {"config": {
        "max_concurrent": 8, "per_step_k8s_config": {"ckm_layers": cluster.gpu_step_k8s_config({"gpu": "a100"}, gpus=2)}}}})
    assert ok["execution"]["k8s"]["max_concurrent"] == 8
    assert ok["execution"]["k8s"]["per_step_k8s_config"]["ckm_layers"]["container_config"]["resources"]["limits"][GPU] == "2"
    for bad in ({"max_concurrent": "many"}, {"per_step_k8s_config": {"ckm_layers": {"container": {}}}}, {"gpus": 1}):
        with pytest.raises(dg.DagsterInvalidConfigError):
            dg.validate_run_config(job, {"execution": {"config": bad}})
    # the executor's own schema accepts the step config a GPU tag carries
    _valid(dagster_k8s.k8s_job_executor.config_schema.config_type,
           {"step_k8s_config": cluster.gpu_step_k8s_config(), "job_namespace": "simart"})


def test_the_tile_keys_docs_cluster_md_backfills_are_partitions_of_ckm_tiles(k8s_defs):
    """docs/cluster.md builds `dagster job backfill --partitions` from the scene's grid; those are
    ckm_tiles partitions, and exactly the tiles the scene uses."""
    from simart_pipeline.ckm.grid import scene_tiles
    from simart_pipeline.config import load_scene_config

    expr = "f'{cfg.name}|{t}' for t in scene_tiles(cfg.ckm)"
    assert expr in (REPO / "docs" / "cluster.md").read_text()
    cfg = load_scene_config(TINY)
    keys = eval(f"[{expr}]", {"cfg": cfg, "scene_tiles": scene_tiles})  # the docs' own expression
    assert keys == ["tiny|r0c0", "tiny|r0c1"]
    instance = dg.DagsterInstance.ephemeral()
    instance.add_dynamic_partitions("scene", ["tiny"])
    partitions = k8s_defs.resolve_job_def("ckm_tiles").partitions_def
    assert set(keys) < set(partitions.get_partition_keys(dynamic_partitions_store=instance))
    assert {str(dg.MultiPartitionKey({"scene": "tiny", "tile": t})) for t in ("r0c0", "r0c1")} == set(keys)


def test_the_code_server_module_loads_in_cluster_mode():
    """What the user deployment runs: the module the gRPC server loads, with the image's environment."""
    env = {**os.environ, "SIMART_EXECUTOR": "k8s", "SIMART_AUTOMATION": "off"}
    out = subprocess.run([sys.executable, "-m", "dagster", "definitions", "validate", "-m", "simart_pipeline.definitions"],
                         capture_output=True, text=True, env=env, cwd=REPO, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    bad = subprocess.run([sys.executable, "-c", "import simart_pipeline.definitions"], capture_output=True, text=True,
                         env={**env, "SIMART_EXECUTOR": "kube"}, cwd=REPO, timeout=300)
    assert bad.returncode != 0 and "SIMART_EXECUTOR: 'kube' is not one of local, k8s" in bad.stderr


# --- steps in their own processes: the multiprocess executor over a real instance ----------------------
SCENE_ASSETS = ["osm_extract", "paired_meshes", "trajectory"]


def scene_assets_job():
    """The job scene_assets (osm_extract, then paired_meshes and trajectory side by side) as a child
    process rebuilds it (dg.build_reconstructable_job); data root from SIMART_DATA."""
    from simart_pipeline.definitions import build_definitions

    job = build_definitions(data_root=os.environ["SIMART_DATA"], executor="local").resolve_job_def("scene_assets")
    assert {k.to_user_string() for k in job.asset_layer.executable_asset_keys} == set(SCENE_ASSETS)
    return job


def _data_versions(instance, scene: str) -> dict:
    out = {}
    for key in SCENE_ASSETS:
        (rec,) = instance.fetch_materializations(
            dg.AssetRecordsFilter(asset_key=dg.AssetKey(key), asset_partitions=[scene]), limit=1).records
        out[key] = rec.asset_materialization.tags["dagster/data_version"]
    return out


def _same_directory(a: Path, b: Path):
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files_a == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file()) and files_a
    for rel in files_a:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel


def test_multiprocess_executor_materialises_the_same_data_as_in_process(tmp_path, monkeypatch):
    from simart_pipeline.assets import ALL_ASSETS
    from simart_pipeline.definitions import build_definitions
    from simart_pipeline.partitions import scene_partitions

    roots = {"multi": tmp_path / "multi", "inproc": tmp_path / "inproc"}
    for root in roots.values():
        registry.register(TINY, root)
    # in process
    inproc = dg.DagsterInstance.ephemeral()
    inproc.add_dynamic_partitions(scene_partitions.name, ["tiny"])
    result = dg.materialize(ALL_ASSETS, selection=SCENE_ASSETS, partition_key="tiny", instance=inproc,
                            resources=build_definitions(data_root=str(roots["inproc"])).resources)
    assert result.success
    # each step in its own process, two at a time, on an instance made from the project's dagster.yaml
    home = tmp_path / "home"
    home.mkdir()
    shutil.copyfile(REPO / "dagster.yaml", home / "dagster.yaml")
    monkeypatch.setenv("SIMART_DATA", str(roots["multi"]))
    with dg.DagsterInstance.from_config(str(home)) as instance:
        instance.add_dynamic_partitions(scene_partitions.name, ["tiny"])
        job = dg.build_reconstructable_job("test_cluster", "scene_assets_job",
                                           reconstructor_working_directory=str(REPO / "tests"))
        with dg.execute_job(job, instance=instance,
                            run_config={"execution": {"config": {"multiprocess": {
                                "max_concurrent": 2,
                                # children fork from a server that imported the project once: seconds, not minutes
                                "start_method": {"forkserver": {"preload_modules": ["simart_pipeline.definitions"]}}}}}},
                            tags={"dagster/partition": "tiny"}) as run:
            assert run.success
            events = run.all_events
            launched = {e.step_key: i for i, e in enumerate(events) if e.event_type_value == "STEP_WORKER_STARTING"}
            done = {e.step_key: i for i, e in enumerate(events) if e.event_type_value == "STEP_SUCCESS"}
            pids = {e.step_key: e.pid for e in events if e.event_type_value == "STEP_START"}
        assert set(SCENE_ASSETS) <= set(launched) and set(SCENE_ASSETS) <= set(pids)
        pids = {k: pids[k] for k in SCENE_ASSETS}
        # a process per step, none of them this one
        assert len(set(pids.values())) == 3 and os.getpid() not in pids.values()
        # max_concurrent 2: the two steps that need only osm_extract were both launched before either ended
        assert max(launched["paired_meshes"], launched["trajectory"]) < min(done["paired_meshes"], done["trajectory"])
        assert launched["osm_extract"] < done["osm_extract"] < min(launched["paired_meshes"], launched["trajectory"])
        assert _data_versions(instance, "tiny") == _data_versions(inproc, "tiny")
    # the same stores, value for value and attribute for attribute
    for asset in ("osm_extract", "trajectory"):
        a, b = (xr.open_zarr(r / asset / "tiny.zarr").load() for r in (roots["multi"], roots["inproc"]))
        xr.testing.assert_identical(a, b)
        assert a.sizes and any(np.asarray(v).size for v in a.data_vars.values())
    _same_directory(roots["multi"] / "paired_meshes" / "tiny", roots["inproc"] / "paired_meshes" / "tiny")
