"""What the viewer sends (issue 18): bytes per client per second, recording size, splat error.

For the default scene and the paper scene (horse_gallop, 50,000 Gaussians), each with the splats
streamed as the whole buffer per frame (``--splat-groups 0``) and as K rigidly moving groups
(``Viewer(splat_groups=K)``): a websocket client (viser's own subprotocol) counts the bytes it
receives while the viewer runs ``--seconds`` of simulated time at 30 viewer frames per
simulated second (frames back to back, so the figure is bytes per simulated second = bytes per
wall second at Speed 1), the same run is recorded (.viser size), then the viewer runs paced in
real time at Speed 1 for ``--realtime`` wall seconds with the client still attached (achieved
simulated s per wall s and frames/s; no browser: the client only receives), and per frame the grouped
stream's fit error (each Gaussian's distance to its group's rigid fit, as a fraction of the
scene's bounding-box diagonal: median, 99th percentile, max) is logged.

    python bench/bench_viewer_stream.py --seconds 10 --groups 0,64,128,256
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from common import describe_device, write_json  # noqa: E402

RESULTS = ROOT / "bench" / "results"


def _count_bytes(port: int, stop: threading.Event, out: dict):
    import viser
    from websockets.sync.client import connect

    ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
    out["bytes"], out["messages"] = 0, 0
    out["connected"].set()
    try:
        while not stop.is_set():
            try:
                raw = ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            out["bytes"] += len(raw)
            out["messages"] += 1
    finally:
        ws.close()


def measure(scene: str, groups: int, seconds: float, device, tmp: Path, realtime_s: float = 0.0) -> dict:
    from dynmesh_warp import build_world, load_scene_config
    from dynmesh_warp.gaussians import gaussians_for_surface
    from dynmesh_warp.viewer import Viewer

    cfg = load_scene_config(ROOT / "examples" / "horse_gallop.yaml") if scene == "horse_gallop" else load_scene_config()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        world = build_world(cfg, device=device)
    world.render_state = True
    g = gaussians_for_surface(world.model.surface.sequence, cfg, world.device)
    rec = tmp / f"{scene}_{groups}.viser"
    t0 = time.perf_counter()
    v = Viewer(world, g, port=0, realtime=False, record=rec, splat_groups=groups, log=lambda *a: None)
    setup_s = time.perf_counter() - t0
    stop, out = threading.Event(), {"connected": threading.Event()}
    th = threading.Thread(target=_count_bytes, args=(v.port, stop, out), daemon=True)
    th.start()
    out["connected"].wait(10)
    time.sleep(0.5)  # the client's initial scene
    initial = out["bytes"]
    frames = int(round(seconds * v.fps))
    errs = []
    t_sim0 = world.time
    t0 = time.perf_counter()
    for _ in range(frames):
        v.update()
        if v.stream is not None:
            errs.append(dict(v.stream.error))
    wall = time.perf_counter() - t0
    sim_s = world.time - t_sim0  # simulated seconds of the recorded, counted frames
    time.sleep(1.0)  # let the client drain
    stop.set()
    th.join(5)
    v.close()
    size = rec.stat().st_size
    # real time: a new viewer (no recording) paced to 30 fps at Speed 1 for `realtime_s` wall
    # seconds with a counting client attached; the achieved simulated s per wall s and frames/s
    rt = {}
    if realtime_s > 0:
        v2 = Viewer(world, g, port=0, realtime=True, splat_groups=groups, log=lambda *a: None,
                    hold_until_client=False)  # the counting client is not a browser (sends no camera)
        stop2, out2 = threading.Event(), {"connected": threading.Event()}
        th2 = threading.Thread(target=_count_bytes, args=(v2.port, stop2, out2), daemon=True)
        th2.start()
        out2["connected"].wait(10)
        time.sleep(0.5)
        b0, s0, w0 = out2["bytes"], world.time, time.perf_counter()
        v2.run(stop=lambda: "done" if time.perf_counter() - w0 > realtime_s else None)
        w1 = time.perf_counter() - w0
        rt = {"realtime_wall_s": w1, "realtime_sim_per_wall": (world.time - s0) / w1,
              "realtime_frames_per_s": v2.frame / w1, "realtime_client_bytes_per_wall_s": (out2["bytes"] - b0) / w1}
        stop2.set()
        th2.join(5)
        v2.close()
    res = {"scene": scene, "gaussians": g.count, "splat_groups": groups,
           "groups_used": None if v.stream is None else v.stream.K, "frames": frames, "simulated_s": sim_s,
           "viewer_setup_s": setup_s, "frames_wall_s": wall, "viewer_frames_per_wall_s": frames / wall,
           "client_initial_bytes": initial, "client_stream_bytes": out["bytes"] - initial,
           "client_bytes_per_s": (out["bytes"] - initial) / max(sim_s, 1e-9),
           "client_messages": out["messages"], "recording_bytes": size,
           "rekeys": None if v.stream is None else v.stream.rekeys, **rt}
    if errs:
        for k in ("median", "p99", "max"):
            a = np.array([e[k] for e in errs])
            res[f"error_{k}_mean"], res[f"error_{k}_worst"] = float(a.mean()), float(a.max())
    print(f"{scene:13s} groups {groups:4d}: {res['client_bytes_per_s'] / 1e6:7.2f} MB/s per client, recording "
          f"{size / 1e6:6.1f} MB for {sim_s:.1f} s, {res['viewer_frames_per_wall_s']:.1f} frames/s"
          + (f", real time: {rt['realtime_sim_per_wall']:.2f} sim s / wall s at {rt['realtime_frames_per_s']:.1f} frames/s"
             if rt else "")
          + (f", error p99 {100 * res['error_p99_mean']:.2f} % (worst {100 * res['error_p99_worst']:.2f} %), max "
             f"{100 * res['error_max_mean']:.2f} % (worst {100 * res['error_max_worst']:.2f} %), rekeys {res['rekeys']}"
             if errs else ""), flush=True)
    return res


def main(argv=None):
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--groups", default="0,64,128,256")
    ap.add_argument("--scenes", default="default,horse_gallop")
    ap.add_argument("--realtime", type=float, default=10.0, help="wall seconds of paced real-time viewing (0: none)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    device = wp.get_device(args.device)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes.split(","):
            if scene == "horse_gallop" and not (ROOT.parent / "shared" / "data" / "horse_gallop.npz").exists():
                print("skip horse_gallop: ../shared/data/horse_gallop.npz not found")
                continue
            for k in [int(x) for x in args.groups.split(",")]:
                rows.append(measure(scene, k, args.seconds, device, Path(tmp), args.realtime))
    out = Path(args.out) if args.out else RESULTS / f"viewer_stream_{'cuda' if device.is_cuda else 'cpu'}.json"
    write_json(out, {"machine": describe_device(device), "seconds": args.seconds, "rows": rows})


if __name__ == "__main__":
    main()
