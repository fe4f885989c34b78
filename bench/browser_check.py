"""Real-browser check of the viewer: headless Chromium opens the live viewer page (and the
self-contained recording .html) and the screenshots must not be blank. The screenshot is
taken over the DevTools protocol after a real-time wait (``--virtual-time-budget`` never settles
on a continuously rendering WebGL page with an open websocket).

    python bench/browser_check.py                      # -> docs/viewer_screenshot.png
    python bench/browser_check.py --html out/rec.html  # also check a recording page

Needs a Chromium binary (``apt-get install -y chromium``); exits with code 77 (skip) when none
is found. A screenshot is "not blank" when it has > 1000 distinct colours and the pixels of the
3D canvas area differ from its background (std dev of luminance > 5 / 255). WebGL runs on
SwiftShader (software), so no GPU is needed.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


def _free_port() -> int:
    import socket

    with socket.socket() as so:
        so.bind(("127.0.0.1", 0))
        return so.getsockname()[1]


def screenshot(chromium: str, url: str, out: Path, wait_s: float = 20.0, size=(1280, 800)) -> Path:
    """Open ``url`` in headless Chromium, wait ``wait_s`` real seconds, save a PNG screenshot.

    The page renders continuously (and keeps a websocket open), so ``--virtual-time-budget``
    with ``--screenshot`` never settles; the screenshot is taken over the DevTools protocol.
    """
    import base64
    import time
    import urllib.request

    from websockets.sync.client import connect

    prof = tempfile.mkdtemp(prefix="chromium-")
    port = _free_port()
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars",
           f"--remote-debugging-port={port}", "--remote-allow-origins=*",
           f"--user-data-dir={prof}", f"--window-size={size[0]},{size[1]}", url]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        ws_url = None
        t_end = time.time() + 30
        while ws_url is None and time.time() < t_end:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=2) as r:
                    pages = [t for t in json.load(r) if t.get("type") == "page"]
                ws_url = pages[0]["webSocketDebuggerUrl"] if pages else None
            except OSError:
                pass
            if ws_url is None:
                time.sleep(0.5)
        if ws_url is None:
            raise RuntimeError("chromium DevTools endpoint did not come up")
        time.sleep(wait_s)
        with connect(ws_url, max_size=None, open_timeout=20) as ws:
            ws.send(json.dumps({"id": 1, "method": "Page.captureScreenshot", "params": {"format": "png"}}))
            while True:
                msg = json.loads(ws.recv(timeout=60))
                if msg.get("id") == 1:
                    break
        out.write_bytes(base64.b64decode(msg["result"]["data"]))
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
        shutil.rmtree(prof, ignore_errors=True)
    return out


def image_stats(png: Path) -> dict:
    import matplotlib.image as mpimg

    img = mpimg.imread(str(png))[..., :3]
    q = np.round(img * 255).astype(np.uint8)
    colours = len(np.unique(q.reshape(-1, 3).view(np.dtype((np.void, 3)))))
    lum = img @ np.array([0.299, 0.587, 0.114])
    h, w = lum.shape
    canvas = lum[:, : int(w * 0.7)]  # the 3D view (the control panel sits on the right)
    return {"width": w, "height": h, "distinct_colours": int(colours), "canvas_lum_std": float(canvas.std()),
            "not_blank": bool(colours > 1000 and canvas.std() > 5 / 255)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default=None, help="scene YAML (default: the built-in default scene)")
    ap.add_argument("--port", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "docs" / "viewer_screenshot.png"))
    ap.add_argument("--html", default=None, help="also screenshot this recording .html (file://)")
    ap.add_argument("--wait", type=float, default=20.0, help="seconds to let the page load and render")
    a = ap.parse_args(argv)
    chromium = find_chromium()
    if chromium is None:
        print("SKIP: no chromium binary (apt-get install -y chromium)")
        return 77
    import warp as wp

    wp.config.quiet = True
    from dynmesh_warp import build_world, load_scene_config
    from dynmesh_warp.gaussians import gaussians_for_world
    from dynmesh_warp.outputs import atomic_path
    from dynmesh_warp.viewer import Viewer

    cfg = load_scene_config(a.scene)
    world = build_world(cfg, device="cpu")
    g = gaussians_for_world(world, cfg)
    v = Viewer(world, g, port=a.port, show_mesh=False, log=lambda *x: None)
    stop = threading.Event()

    def loop():
        while not stop.is_set():
            v.update()
            stop.wait(v.frame_dt)

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    report = {"chromium": subprocess.run([chromium, "--version"], capture_output=True, text=True).stdout.strip()}
    try:
        with atomic_path(a.out, suffix=".png") as tmp:
            screenshot(chromium, f"http://127.0.0.1:{v.port}/", tmp, a.wait)
            report["live"] = image_stats(tmp)
            report["live"]["frames_served"] = v.frame
            if not report["live"]["not_blank"]:
                raise RuntimeError(f"live viewer screenshot looks blank: {report['live']}")
    finally:
        stop.set()
        th.join(timeout=5)
        v.close()
    report["live"]["screenshot"] = a.out
    if a.html:
        out2 = Path(tempfile.mkdtemp()) / "recording.png"
        screenshot(chromium, Path(a.html).resolve().as_uri(), out2, a.wait)
        report["recording_html"] = dict(image_stats(out2), screenshot=str(out2))
    print(json.dumps(report, indent=2))
    ok = report["live"]["not_blank"] and report.get("recording_html", {"not_blank": True})["not_blank"]
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
