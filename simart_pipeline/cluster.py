"""Running the same Definitions on Kubernetes (``docs/cluster.md``): one pod per step.

``SIMART_EXECUTOR=k8s`` in the code location's environment (``deploy/helm/values.yaml`` sets it), or
``build_definitions(executor="k8s")``, selects Dagster's ``k8s_job_executor`` (from the optional
``cluster`` extra, dagster-k8s) and gives every step of an asset in a GPU pool (``raytracing``:
Sionna RT; ``rendering``: the Mitsuba sensor renderer) a ``dagster-k8s/config`` op tag that requests
one ``nvidia.com/gpu`` and puts its pod on a GPU node. Unset (or ``local``), nothing changes: the
default executor, no tags. The pods find the data and the scenes where the Helm values mount the
shared ReadWriteMany volume, through ``SIMART_DATA`` and ``SIMART_SCENES``.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterable, Mapping

import dagster as dg

EXECUTORS = ("local", "k8s")
GPU_POOLS = ("raytracing", "rendering")  # the pools whose steps run on a GPU node in a cluster
K8S_CONFIG_TAG = "dagster-k8s/config"
GPU_RESOURCE = "nvidia.com/gpu"
# The label NVIDIA's GPU feature discovery (GPU operator) puts on every node with a GPU.
DEFAULT_GPU_NODE_SELECTOR = "nvidia.com/gpu.present=true"
INSTALL_HINT = ("the Kubernetes deployment needs the optional `cluster` extra (dagster-k8s): "
                "pip install -e '.[cluster]' (bash scripts/bootstrap.sh setup installs it)")


def executor_mode(value: str | None = None) -> str:
    """``value``, else ``$SIMART_EXECUTOR``, else ``local``; anything else is an error naming both."""
    mode = (value if value is not None else os.environ.get("SIMART_EXECUTOR", "")).strip() or "local"
    if mode not in EXECUTORS:
        raise ValueError(f"SIMART_EXECUTOR: {mode!r} is not one of {', '.join(EXECUTORS)}")
    return mode


def parse_node_selector(text: str) -> dict[str, str]:
    """``key=value[,key=value...]`` (``$SIMART_GPU_NODE_SELECTOR``) as a node selector."""
    out = {}
    for item in filter(None, (p.strip() for p in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"SIMART_GPU_NODE_SELECTOR: {item!r} is not key=value")
        out[key.strip()] = value.strip()
    return out


def gpu_node_selector() -> dict[str, str]:
    return parse_node_selector(os.environ.get("SIMART_GPU_NODE_SELECTOR", DEFAULT_GPU_NODE_SELECTOR))


def gpu_step_k8s_config(node_selector: Mapping[str, str] | None = None, gpus: int = 1) -> dict:
    """The ``dagster-k8s/config`` of a GPU step: ``gpus`` GPUs requested and limited (Kubernetes
    wants both equal for an extended resource), a node selector, and a toleration of the
    ``nvidia.com/gpu`` taint that managed clusters put on GPU nodes."""
    return {
        "container_config": {"resources": {"requests": {GPU_RESOURCE: str(gpus)},
                                           "limits": {GPU_RESOURCE: str(gpus)}}},
        "pod_spec_config": {
            "node_selector": dict(gpu_node_selector() if node_selector is None else node_selector),
            "tolerations": [{"key": GPU_RESOURCE, "operator": "Exists", "effect": "NoSchedule"}],
        },
    }


def _with_op_tags(assets_def: dg.AssetsDefinition, tags: Mapping[str, object]) -> dg.AssetsDefinition:
    """``assets_def`` whose op carries ``tags`` as well (the step tags the k8s executor reads);
    specs, code versions, pools and checks stay as they are."""
    op = assets_def.op
    attrs = assets_def.get_attributes_dict()
    with warnings.catch_warnings():
        # OpDefinition.version is deprecated (2.0) with no public successor; execution_type is beta:
        # both are passed on unchanged.
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", dg.BetaWarning)
        attrs["node_def"] = dg.OpDefinition(
            compute_fn=op.compute_fn, name=op.name,
            ins={d.name: dg.In.from_definition(d) for d in op.input_defs},
            outs={d.name: dg.Out.from_definition(d) for d in op.output_defs},
            description=op.description, config_schema=op.config_schema,
            required_resource_keys=op.required_resource_keys, tags={**op.tags, **tags},
            code_version=op.version, retry_policy=op.retry_policy, pool=op.pool)
        return assets_def.__class__(**attrs)


def gpu_tagged(assets: Iterable, node_selector: Mapping[str, str] | None = None) -> list:
    """``assets`` with the GPU step config tagged on every asset whose op is in a GPU pool."""
    config = gpu_step_k8s_config(node_selector)
    return [_with_op_tags(a, {K8S_CONFIG_TAG: config})
            if isinstance(a, dg.AssetsDefinition) and a.is_executable and a.op.pool in GPU_POOLS else a
            for a in assets]


def k8s_executor():
    """dagster-k8s's ``k8s_job_executor`` (one Kubernetes Job per step), or an ImportError that says
    how to install it."""
    try:
        from dagster_k8s import k8s_job_executor
    except ImportError as exc:
        raise ImportError(INSTALL_HINT) from exc
    return k8s_job_executor
