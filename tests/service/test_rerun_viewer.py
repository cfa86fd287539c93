"""rerun the way rerun users expect: a `semloc up` run is one recording with the viewer layout, saved per node
(``--rerun-save``) or served to the web viewer (``--serve-web``), which a real headless browser opens."""

from __future__ import annotations

import base64
import re
import shutil
import signal
from pathlib import Path

import pytest
import rerun as rr

from tests.service.conftest import free_port, make_image_folder, read_jsonl, wait_until

pytestmark = pytest.mark.service

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
FRAMES = 20
# Views of services/blueprint.py (and where they look): the layout is the one declared there, not rerun's default.
LAYOUT_VIEWS = {"camera": "/r1/camera/image", "detector heatmaps": "/r1/detector/heatmap",
                "map: particles, estimate (blue), ground truth (green)": "/r1/localizer"}


def layout_views(reader: rr.chunk.RrdReader, blueprint) -> dict[str, str]:
    """View name -> space origin of a blueprint store."""
    names: dict[str, str] = {}
    origins: dict[str, str] = {}
    for chunk in reader.stream(store=blueprint):
        batch = chunk.to_record_batch()
        for column, found in (("ViewBlueprint:display_name", names), ("ViewBlueprint:space_origin", origins)):
            if column in batch.schema.names:
                found[chunk.entity_path] = batch.column(column).to_pylist()[-1][0]
    return {names[view]: origins.get(view) for view in names}


def image_rows(reader: rr.chunk.RrdReader) -> int:
    return sum(c.num_rows for c in reader.stream() if c.entity_path == "/r1/camera/image" and not c.is_static)


def start_up(procs, tmp_path: Path, *rerun_options: str):
    make_image_folder(tmp_path / "images", FRAMES)
    sink_log = tmp_path / "sink.jsonl"
    up = procs.semloc("up", str(DEPLOY / "camera-sink.yaml"), "--hub", f"tcp/127.0.0.1:{free_port()}",
                      "--run-dir", str(tmp_path / "run"), "--set", f"nodes.camera.config.source={tmp_path / 'images'}",
                      "--set", "nodes.camera.config.loop=false", "--set", "nodes.camera.config.rate=20",
                      "--set", "nodes.camera.config.wait_for_subscriber_s=60",
                      "--set", f"nodes.sink.config.log_path={sink_log}", *rerun_options, name="up")
    run_id = wait_until(lambda: (m := re.search(r"^run (\S+):", procs.log("up"), re.M)) and m.group(1), 60,
                        message="the run's id")
    wait_until(lambda: len(read_jsonl(sink_log)) >= FRAMES, 120, message=f"{FRAMES} frames at the sink")
    return up, run_id


def stop(up, procs) -> None:
    up.send_signal(signal.SIGINT)
    assert up.wait(60) == 0, procs.log("up")


def test_rerun_save_is_one_recording_with_the_layout(tmp_path, procs):
    up, run_id = start_up(procs, tmp_path, "--rerun-save", str(tmp_path / "rerun"))
    stop(up, procs)
    files = sorted((tmp_path / "rerun").glob("*.rrd"))
    assert [f.name for f in files] == ["camera.rrd", "sink.rrd"]
    for path in files:
        reader = rr.chunk.RrdReader(str(path))
        assert [(r.application_id, r.recording_id) for r in reader.recordings()] == [("semloc", run_id)], path
        [blueprint] = reader.blueprints()
        assert blueprint.application_id == "semloc"
        assert LAYOUT_VIEWS.items() <= layout_views(reader, blueprint).items(), path
    assert image_rows(rr.chunk.RrdReader(str(files[0]))) == FRAMES


def _browser():
    sync_api = pytest.importorskip("playwright.sync_api")
    executable = next(filter(None, map(shutil.which, ("chromium", "chromium-browser", "google-chrome"))), None)
    if executable is None:
        pytest.skip("no Chromium on this machine (Debian: apt-get install chromium)")
    return sync_api, executable


def test_serve_web_shows_the_run_in_a_headless_browser(tmp_path, procs):
    """The page of `semloc up --serve-web` loads the viewer, which receives the run over gRPC-web: the recording it
    holds (its own export, ``save_recording``) has the run's id and every frame; its layout is semloc's."""
    sync_api, executable = _browser()
    web_port, grpc_port = free_port(), free_port()
    up, run_id = start_up(procs, tmp_path, "--serve-web", str(web_port), "--set", f"rerun.grpc_port={grpc_port}")
    url = re.search(r"^rerun web viewer: (\S+)", procs.log("up"), re.M).group(1)
    assert url.startswith(f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}")

    def page_export(page, method: str) -> Path:
        data = page.evaluate(f"""() => {{ const bytes = window._handle.{method}(); let text = "";
            for (let i = 0; i < bytes.length; i += 8192) text += String.fromCharCode(...bytes.subarray(i, i + 8192));
            return btoa(text); }}""")
        path = tmp_path / f"{method}.rrd"
        path.write_bytes(base64.b64decode(data))
        return path

    with sync_api.sync_playwright() as playwright:
        # SwiftShader's WebGL: no GPU here. Nothing but loopback is reached (the page also asks for analytics).
        browser = playwright.chromium.launch(executable_path=executable, args=[
            "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
        try:
            page = browser.new_page(viewport={"width": 480, "height": 320})  # little to draw in software
            page.route(re.compile(r"^(?!https?://127\.0\.0\.1[:/])"), lambda route: route.abort())
            page.goto(url + "&renderer=webgl")
            page.wait_for_function("window._handle !== undefined && !window._handle.has_panicked()",
                                   timeout=240_000)

            def received_all():
                try:
                    reader = rr.chunk.RrdReader(str(page_export(page, "save_recording")))
                    return reader if image_rows(reader) >= FRAMES else None
                except Exception:  # no recording yet
                    return None

            reader = wait_until(received_all, 120, interval=1.0, message=f"{FRAMES} images in the page's recording")
            blueprint_file = page_export(page, "save_blueprint")
        finally:
            browser.close()
    stop(up, procs)
    assert [(r.application_id, r.recording_id) for r in reader.recordings()] == [("semloc", run_id)]
    assert image_rows(reader) == FRAMES
    blueprint_reader = rr.chunk.RrdReader(str(blueprint_file))
    [blueprint] = blueprint_reader.blueprints()
    assert LAYOUT_VIEWS.items() <= layout_views(blueprint_reader, blueprint).items()


def test_connect_without_a_viewer_says_so(tmp_path, capsys, monkeypatch):
    """`semloc up --connect` before `rerun` runs: the nodes would log "streaming to" a URL nothing listens at, so the
    launcher warns; with something listening there, no warning."""
    import socket

    from services.cli import main
    from services.launcher import Launcher

    monkeypatch.setattr(Launcher, "start", lambda self: self)  # the check precedes the launch: no nodes needed
    monkeypatch.setattr(Launcher, "finished", lambda self: True)
    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"
    assert main(["up", "camera-sink", "--connect", url, "--run-dir", str(tmp_path / "none")]) == 0
    assert f"rerun: no viewer listens at {url}: start it first (`rerun`)" in capsys.readouterr().err
    with socket.create_server(("127.0.0.1", 0)) as viewer:
        url = f"rerun+http://127.0.0.1:{viewer.getsockname()[1]}/proxy"
        assert main(["up", "camera-sink", "--connect", url, "--run-dir", str(tmp_path / "one")]) == 0
    assert "no viewer listens" not in capsys.readouterr().err
