"""A real browser on the real UI: `simart dev` serves a copy of tests/scenes/tiny, Debian's Chromium
driven by Playwright backfills the scene's CKM tiles and map from the asset graph's launch dialog,
watches the backfill run and succeed, and finds the CKM map's picture in its latest materialisation.

Needs Debian's ``chromium`` (``apt-get install chromium``; ``bash scripts/bootstrap.sh test`` installs
it) and ``playwright`` from PyPI (the ``test`` extra); Playwright's own browser download is not
used. Without either the test fails and says how to install it. Screenshots go to
``test-artifacts/browser/`` (git-ignored), or to ``$SIMART_BROWSER_ARTIFACTS``, with the dev
server's log."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from conftest import REPO, TESTS, free_port, processes_with_env
from simart_pipeline.cli import DEV_STOP_GRACE_S

ARTIFACTS = Path(os.environ.get("SIMART_BROWSER_ARTIFACTS") or REPO / "test-artifacts" / "browser")
SCENE_TILES = ["r0c0", "r0c1"]  # the tiles tests/scenes/tiny's CKM grid uses (ckm.tiles [2, 1])
UI_TIMEOUT_MS = 60_000  # one UI step on a loaded 2-core machine
BACKFILL_TIMEOUT_S = 420  # three runs; about 90 s on 2 idle cores
PHASES: dict[str, float] = {}  # seconds each phase took, written beside the screenshots

# What the dev server's instance holds before the browser opens it: the scene registered and its
# partition added, as the new_scenes sensor does (automation is off, so nothing runs by itself), and
# the CKM's scene-level upstream (osm_extract, paired_meshes) materialised, so the UI backfill is
# the CKM tiles and the map.
PREPARE = """
import dagster as dg
from simart_pipeline import registry
from simart_pipeline.assets.automation import scan_scenes
from simart_pipeline.cli import _prepare_dagster_home
from simart_pipeline.definitions import build_definitions
from simart_pipeline.partitions import scene_partitions

_prepare_dagster_home()
instance = dg.DagsterInstance.get()
added, problems, _ = scan_scenes(instance, None)
assert added == ["tiny"] and not problems, (added, problems)
instance.add_dynamic_partitions(scene_partitions.name, added)
defs = build_definitions(data_root=str(registry.default_data_root()))
result = dg.materialize(list(defs.assets), selection=dg.AssetSelection.assets("osm_extract", "paired_meshes"),
                        partition_key="tiny", instance=instance, resources=defs.resources)
assert result.success
"""


@pytest.fixture(scope="module")
def chromium() -> str:
    """Debian's Chromium and Playwright, or a failure that says how to install them (never a skip)."""
    path = os.environ.get("SIMART_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
    if not os.access(path, os.X_OK):
        pytest.fail(f"no Chromium at {path}: install Debian's package (`sudo apt-get install chromium`; "
                    "`bash scripts/bootstrap.sh test` does it) or set SIMART_CHROMIUM to a Chromium binary",
                    pytrace=False)
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        pytest.fail("playwright is not installed: `.venv/bin/python -m pip install -e '.[test]'` "
                    "(`bash scripts/bootstrap.sh test` does it); its browser download is not needed",
                    pytrace=False)
    return path


def _gql(base: str, query: str, variables: dict | None = None) -> dict:
    req = urllib.request.Request(f"{base}/graphql", json.dumps({"query": query, "variables": variables or {}}).encode(),
                                 {"content-type": "application/json"})
    with urllib.request.urlopen(req, timeout=30) as r:
        body = json.load(r)
    assert "errors" not in body, body
    return body["data"]


def _backfill_runs(base: str, backfill_id: str) -> list[dict]:
    q = """query($tags: [ExecutionTag!]) { runsOrError(filter: {tags: $tags}) { ... on Runs { results {
           runId status tags { key value } } } } }"""
    runs = _gql(base, q, {"tags": [{"key": "dagster/backfill", "value": backfill_id}]})["runsOrError"]["results"]
    for r in runs:
        r["partition"] = next((t["value"] for t in r["tags"] if t["key"] == "dagster/partition"), None)
    return runs


@pytest.fixture(scope="module")
def dev_ui(chromium, tmp_path_factory):
    """``simart dev`` on 127.0.0.1 with a temporary DAGSTER_HOME, data root and scenes folder (a
    copy of tests/scenes/tiny): (base URL, data root). Stopped by SIGINT at the end; anything of it
    still alive after that is killed by pid, and the teardown fails if something outlived it."""
    tmp = tmp_path_factory.mktemp("browser")
    scenes, data, home = tmp / "scenes", tmp / "data", tmp / "dagster_home"
    shutil.copytree(TESTS / "scenes" / "tiny", scenes / "tiny")
    env = {**os.environ, "DAGSTER_HOME": str(home), "SIMART_DATA": str(data), "SIMART_SCENES": str(scenes),
           "SIMART_AUTOMATION": "off"}
    t0 = time.monotonic()
    prep = subprocess.run([sys.executable, "-c", PREPARE], env=env, cwd=REPO, capture_output=True, text=True,
                          timeout=300)
    assert prep.returncode == 0, f"preparing the instance failed:\n{prep.stderr[-4000:]}"
    PHASES["prepare instance and upstream"], t0 = time.monotonic() - t0, time.monotonic()
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    with open(ARTIFACTS / "dev-server.log", "wb") as log:
        p = subprocess.Popen([sys.executable, "-m", "simart_pipeline.cli", "dev", "--", "--host", "127.0.0.1",
                              "--port", str(port)], env=env, cwd=REPO, stdout=log, stderr=subprocess.STDOUT,
                             start_new_session=True)
    try:
        deadline = time.monotonic() + 180
        while True:
            assert p.poll() is None, f"simart dev exited before serving; see {ARTIFACTS / 'dev-server.log'}"
            try:
                with urllib.request.urlopen(f"{base}/server_info", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            assert time.monotonic() < deadline, "the UI did not answer within 180 s"
            time.sleep(1)
        PHASES["simart dev up"] = time.monotonic() - t0
        yield base, data
    finally:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)  # simart dev stops dagster dev's whole process group
            try:
                p.wait(timeout=DEV_STOP_GRACE_S + 10)
            except subprocess.TimeoutExpired:
                pass
        left = processes_with_env(home)
        for pid in left:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        try:
            os.killpg(p.pid, signal.SIGKILL)  # our own session: nothing should be in it any more
        except ProcessLookupError:
            pass
        p.wait()
        time.sleep(1)
        assert processes_with_env(home) == [], "a process of simart dev survived SIGKILL"
        assert not left, f"simart dev left processes {left} running after SIGINT"


def _dismiss_first_run_dialogs(page) -> None:
    """The first visit shows "Join the Dagster community" (Skip); close it and any other dialog."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        page.get_by_role("dialog").first.wait_for(state="visible", timeout=15_000)
    except PlaywrightTimeout:
        return  # none came
    for _ in range(5):
        dialogs = page.get_by_role("dialog")
        if dialogs.count() == 0:
            return
        for name in ("Skip", "Dismiss", "Close", "Got it", "No thanks"):
            button = dialogs.first.get_by_role("button", name=name, exact=True)
            if button.count():
                button.first.click()
                break
        else:
            raise AssertionError(f"a first-run dialog with no known way out: {dialogs.first.inner_text()!r}")
        page.wait_for_timeout(1000)
    raise AssertionError("first-run dialogs kept coming")


def _pick_partitions(page, dialog, index: int, keys: list[str]) -> None:
    """Tick ``keys`` in the dialog's ``index``-th partition selector (scene, then tile)."""
    from playwright.sync_api import expect

    dialog.get_by_text("Select a partition or create one").nth(index).click()
    for key in keys:
        page.get_by_placeholder("Filter partitions").fill(key)
        page.locator("span").filter(has_text=re.compile(f"^{re.escape(key)}$")).click()
    dialog.get_by_text("Launch runs to materialize", exact=False).click()  # closes the selector's popover
    expect(page.get_by_placeholder("Filter partitions")).to_have_count(0)


def test_backfill_ckm_from_the_ui_and_see_its_map(dev_ui, chromium):
    from playwright.sync_api import expect, sync_playwright

    base, data = dev_ui
    shots = {}

    t_last = time.monotonic()

    def shot(page, name):
        nonlocal t_last
        shots[name] = ARTIFACTS / name
        page.screenshot(path=shots[name])
        PHASES[f"until {name}"], t_last = time.monotonic() - t_last, time.monotonic()

    expect.set_options(timeout=UI_TIMEOUT_MS)
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium)
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.set_default_timeout(UI_TIMEOUT_MS)

            # the asset graph, narrowed to the CKM assets (the selection is part of the route)
            page.goto(f"{base}/asset-groups")
            _dismiss_first_run_dialogs(page)
            expect(page.get_by_text("Global asset lineage")).to_be_visible()
            expect(page.get_by_role("dialog")).to_have_count(0)
            page.goto(f"{base}/asset-groups~{urllib.parse.quote('key:ckm_layers or key:ckm_map')}/")
            for name in ("ckm_layers", "ckm_map"):
                expect(page.get_by_text(name, exact=True).last).to_be_visible()
            expect(page.get_by_role("dialog")).to_have_count(0)  # skipped once, gone for the session
            shot(page, "01-asset-graph.png")

            # the launch dialog: the scene's tiles of ckm_layers, and what depends on them (ckm_map)
            page.get_by_role("button", name="Materialize all").click()
            dialog = page.get_by_role("dialog").filter(has_text="Launch runs to materialize 2 assets")
            expect(dialog).to_be_visible()
            _pick_partitions(page, dialog, 0, ["tiny"])
            _pick_partitions(page, dialog, -1, SCENE_TILES)
            launch = dialog.get_by_role("button", name="Launch backfill")
            expect(launch).to_be_enabled()
            shot(page, "02-launch-backfill.png")
            launch.click()

            toast = page.get_by_text(re.compile(r"Created backfill \w+"))
            expect(toast).to_be_visible()
            backfill_id = re.search(r"Created backfill (\w+)", toast.inner_text()).group(1)
            page.goto(f"{base}/runs/b/{backfill_id}")
            status = page.get_by_text("Status", exact=True).locator("xpath=following-sibling::*[1]")

            # while it runs: wait for a run of it to be executing, then show the backfill page
            deadline = time.monotonic() + BACKFILL_TIMEOUT_S
            while not any(r["status"] == "STARTED" for r in _backfill_runs(base, backfill_id)):
                assert time.monotonic() < deadline, "no run of the backfill started"
                time.sleep(1)
            page.reload()
            expect(status).to_have_text("In progress")
            shot(page, "03-backfill-running.png")

            # until it ends (the page refreshes itself; a reload now and then makes sure)
            while not re.fullmatch(r"Succeeded|Failed|Canceled|Canceling|Completed.*", status.inner_text().strip()):
                assert time.monotonic() < deadline, \
                    f"the backfill did not end within {BACKFILL_TIMEOUT_S} s (status {status.inner_text()!r})"
                page.wait_for_timeout(5000)
                page.reload()
                status.wait_for()
            shot(page, "04-backfill-done.png")
            expect(status).to_have_text("Succeeded")
            runs = _backfill_runs(base, backfill_id)
            assert sorted(r["partition"] for r in runs) == sorted([*(f"tiny|{t}" for t in SCENE_TILES), "tiny"]), runs
            assert {r["status"] for r in runs} == {"SUCCESS"}, runs

            # the CKM map's latest materialisation: every tile complete, and its picture
            page.goto(f"{base}/assets/ckm_map")
            row = page.get_by_role("row").filter(has_text="sunny_tiles_complete")
            expect(row).to_contain_text(f"{len(SCENE_TILES)}/{len(SCENE_TILES)}")
            page.get_by_role("row").filter(has_text="sunny_map").get_by_text("[Show Markdown]").click()
            md = page.get_by_role("dialog").filter(has_text="sunny_map")
            picture = md.locator("img")
            expect(picture).to_be_visible()
            expect(picture).to_have_attribute("src", re.compile(r"^data:image/png;base64,"))
            width, height = picture.evaluate("img => [img.naturalWidth, img.naturalHeight]")
            assert width >= 400 and height >= 300, (width, height)  # a decoded picture, not a broken icon
            box = picture.bounding_box()
            assert box and box["width"] >= 400 and box["height"] >= 300, box  # shown at a readable size
            page.wait_for_timeout(1000)  # the dialog's fade-in
            shot(page, "05-ckm-map.png")
        finally:
            browser.close()

    # the stores the UI's backfill wrote: both tiles of both maps complete
    from simart_pipeline.ckm import mosaic
    from simart_pipeline.ckm.grid import parse_tile_key
    from simart_pipeline.ckm.maps import map_path

    for name in ("sunny", "rainy"):
        done = mosaic.open_map(map_path(data, "tiny", name))["tile_complete"].values
        assert all(done[parse_tile_key(t)] for t in SCENE_TILES), (name, done)
    for path in shots.values():
        assert path.stat().st_size > 10_000, path  # a page, not a blank
    (ARTIFACTS / "timings.txt").write_text("".join(f"{v:6.1f} s  {k}\n" for k, v in PHASES.items()))
