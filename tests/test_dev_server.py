"""`simart dev` serves the UI and stops cleanly on SIGINT and on SIGTERM: the whole process group
within seconds."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import urllib.request

import pytest

from conftest import free_port, processes_with_env
from simart_pipeline.cli import DEV_STOP_GRACE_S


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_simart_dev_serves_and_stops_on_signal(tmp_path, signum):
    home, port = tmp_path / "dagster_home", free_port()
    # automation off: the sensors would start materialising the repository's scenes
    env = {**os.environ, "DAGSTER_HOME": str(home), "SIMART_DATA": str(tmp_path / "data"), "SIMART_AUTOMATION": "off"}
    p = subprocess.Popen([sys.executable, "-m", "simart_pipeline.cli", "dev", "--", "--host", "127.0.0.1",
                          "--port", str(port)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 180
        while True:
            assert p.poll() is None, "simart dev exited before serving"
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/server_info", timeout=2) as r:
                    assert r.status == 200
                    break
            except OSError:
                assert time.monotonic() < deadline, "the UI did not answer within 180 s"
                time.sleep(1)
        assert len(processes_with_env(home)) >= 2  # simart, dagster dev and its webserver and daemon
        t0 = time.monotonic()
        p.send_signal(signum)
        p.wait(timeout=DEV_STOP_GRACE_S + 10)
        took = time.monotonic() - t0
        assert took < DEV_STOP_GRACE_S + 5, took
        time.sleep(1)
        assert processes_with_env(home) == [], "a process of simart dev outlived it"
        assert p.returncode == 128 + signum
    finally:
        if p.poll() is None:
            p.kill()
        for pid in processes_with_env(home):
            os.kill(pid, signal.SIGKILL)
