"""The beam-prediction case study as an asset (docs/beam-study.md): a scene whose config has a
``beam_study`` section gets its table, plot, report.md and results.json."""

import json
import time

import dagster as dg

from simart_pipeline import previews, stores
from simart_pipeline.assets.versioning import code_version, config_dep, versioned_result
from simart_pipeline.partitions import from_scene, scene_partitions
from simart_pipeline.resources import ProjectResource


@dg.asset(partitions_def=scene_partitions, code_version=code_version("beam_prediction"), group_name="study",
          deps=[config_dep("beam_prediction"), "trajectory",
                dg.AssetDep("kpis", partition_mapping=from_scene),
                dg.AssetDep("sensor_frames", partition_mapping=from_scene)])
def beam_prediction(context: dg.AssetExecutionContext, project: ProjectResource) -> dg.MaterializeResult:
    """Vision- and position-aided beam prediction: the UAV detected in the base-station camera's
    frames of every weather, its image box and GPS fix predict the best beam; top-1/3/5 per weather
    against the paper's, with position-only, vision-only and ground-truth-box rows."""
    from simart_pipeline.study import beam_prediction as bp

    scene = context.partition_key
    cfg = project.config(scene)
    st = cfg.beam_study
    if st is None:
        raise dg.Failure(f"{scene}: scene.yaml has no beam_study section; this asset is only for such scenes")
    t0 = time.perf_counter()
    trajectory = stores.open_store(stores.store_path(project.data_root, "trajectory", scene))
    passages, num_flights = bp.flights_of(cfg, trajectory)
    samples = []
    for weather in cfg.weathers:
        kpis = stores.open_store(stores.store_path(project.data_root, "kpis", scene, weather))
        frames = stores.open_store(stores.store_path(project.data_root, "sensor_frames", scene, weather), tree=True)
        samples.append(bp.load_samples(cfg, weather, kpis, frames[f"{st.base_station}/{st.camera}"].to_dataset(),
                                       frames[f"{st.platform}/{st.gps}"].to_dataset(), passages))
    train, test = bp.split_flights(num_flights, st.test_fraction, st.seed)
    results = bp.run_study(samples, train, test, seed=st.seed, margin_px=st.match_margin_px, trees=st.classifier_trees)
    results["scene"] = scene
    results["seed"] = st.seed
    results["run_time_s"] = round(time.perf_counter() - t0, 1)
    out = stores.store_path(project.data_root, "beam_prediction", scene, suffix="")
    fig = bp.figure(results, title=f"{scene}: beam prediction (test flights)")
    report = bp.report_markdown(results, scene)

    def fill(tmp):
        fig.savefig(tmp / "beam_prediction.png", dpi=110)
        (tmp / "report.md").write_text(report + "\n![beam prediction](beam_prediction.png)\n")
        (tmp / "results.json").write_text(json.dumps({k: v for k, v in results.items() if k != "gain_loss_db"},
                                                     indent=2, sort_keys=True))

    stores.write_directory(out, fill)
    fused = results["beam_prediction"]["position+vision"]
    meta = {"path": str(out), "train_flights": str(train.tolist()), "test_flights": str(test.tolist()),
            **{f"top1_{w}": round(100 * r["top1"], 2) for w, r in fused.items()},
            **{f"detection_rate_{w}": round(100 * r["detection_rate"], 2)
               for w, r in results["detection"]["difference"].items()},
            "report": dg.MetadataValue.md(report), "picture": dg.MetadataValue.md(previews.figure_markdown(fig))}
    return versioned_result(context, project, "beam_prediction", meta)
