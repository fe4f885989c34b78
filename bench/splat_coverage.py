"""Do the splats read as a surface? Coverage of the mesh's silhouette by splat alpha (issue 18).

For the default scene and the paper scene (horse_gallop), the Gaussians the viewer shows
(``gaussians_for_surface`` with the scene's ``gaussians`` section) are rendered with our
renderer (``render.render_world``, the same EWA splatting as viser's, with its 0.3 px
dilation) from ``--views`` cameras orbiting the surface, at several moments; the mesh's
silhouette in the same cameras is found by ray casting the surface (``wp.mesh_query_ray``, one
ray per pixel). Reported per scene: the mean splat alpha over the silhouette's pixels (the
fraction of the silhouette the splats cover; issue 18 asks >= 0.99), the fraction of
silhouette pixels with alpha < 0.5 (holes), and the worst view.

    python bench/splat_coverage.py --views 8 --size 320
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from common import describe_device, write_json  # noqa: E402

from dynmesh_warp.kernels.render import pixel_ray  # noqa: E402

RESULTS = ROOT / "bench" / "results"


@wp.kernel
def cast_silhouette(
    # In:
    mesh: wp.uint64,
    view_rotation: wp.array[wp.mat33],
    view_translation: wp.array[wp.vec3],
    intrinsics: wp.array[wp.vec4],
    # Out:
    hit: wp.array3d[wp.int32],
):
    """1 where the pixel's ray meets the mesh (launch (C, H, W); OpenCV pinhole, world-to-camera
    R, t; intrinsics fx, fy, cx, cy [px])."""
    c, py, px = wp.tid()
    o, d, dc = pixel_ray(intrinsics[c], view_rotation[c], view_translation[c], px, py)
    q = wp.mesh_query_ray(mesh, o, d, 1.0e6)
    hit[c, py, px] = wp.where(q.result, 1, 0)


def coverage(scene: str, views: int, size: int, moments: int, device) -> dict:
    from dynmesh_warp import build_world, load_scene_config
    from dynmesh_warp.gaussians import gaussians_for_surface
    from dynmesh_warp.render import Renderer, orbit_cameras, render_world

    cfg = load_scene_config(ROOT / "examples" / "horse_gallop.yaml") if scene == "horse_gallop" else load_scene_config()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        world = build_world(cfg, device=device, collider="refit")
    world.render_state = True
    g = gaussians_for_surface(world.model.surface.sequence, cfg, world.device)
    seq = world.model.surface.sequence
    V0 = seq.V[0]
    center = 0.5 * (V0.min(0) + V0.max(0))
    diag = float(np.linalg.norm(np.ptp(V0, axis=0)))
    cams = orbit_cameras(center, 1.1 * diag, views, elevation_deg=25.0, width=size, height=size * 3 // 4)
    r = Renderer(device)
    duration = seq.num_frames / seq.fps
    rows = []
    for t in np.linspace(0.0, duration, moments, endpoint=False):
        world.set_time(float(t))
        world.sync_surface()
        g.update(world.surface_points(), world.surface_indices())
        out = render_world(world, g, cams, renderer=r)
        alpha = out.alpha.numpy()
        mesh = wp.Mesh(points=wp.clone(world.surface_points()), indices=world.surface_indices())
        Rs, ts, ks = r._camera_arrays(cams)
        hit = wp.zeros((len(cams), cams[0].height, cams[0].width), dtype=wp.int32, device=device)
        wp.launch(cast_silhouette, hit.shape, inputs=[mesh.id, Rs, ts, ks], outputs=[hit], device=device)
        sil = hit.numpy().astype(bool)
        for c in range(len(cams)):
            a = alpha[c][sil[c]]
            rows.append({"time": float(t), "view": c, "silhouette_px": int(sil[c].sum()),
                         "mean_alpha": float(a.mean()), "holes_below_0.5": float((a < 0.5).mean()),
                         "below_0.9": float((a < 0.9).mean())})
    mean = float(np.mean([x["mean_alpha"] for x in rows]))
    worst = min(rows, key=lambda x: x["mean_alpha"])
    res = {"scene": scene, "gaussians": g.count, "views": views, "moments": moments, "size": [size, size * 3 // 4],
           "mean_alpha_over_silhouette": mean, "worst_view": worst,
           "holes_below_0.5_mean": float(np.mean([x["holes_below_0.5"] for x in rows])), "per_view": rows}
    print(f"{scene:13s} {g.count:6d} Gaussians: silhouette covered {100 * mean:.2f} % (mean alpha), worst view "
          f"{100 * worst['mean_alpha']:.2f} %, holes (alpha < 0.5) {100 * res['holes_below_0.5_mean']:.2f} % of it",
          flush=True)
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--moments", type=int, default=4)
    ap.add_argument("--size", type=int, default=320)
    ap.add_argument("--scenes", default="default,horse_gallop")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    wp.config.quiet = True
    device = wp.get_device(args.device)
    rows = []
    for scene in args.scenes.split(","):
        if scene == "horse_gallop" and not (ROOT.parent / "shared" / "data" / "horse_gallop.npz").exists():
            print("skip horse_gallop: ../shared/data/horse_gallop.npz not found")
            continue
        rows.append(coverage(scene, args.views, args.size, args.moments, device))
    out = Path(args.out) if args.out else RESULTS / f"splat_coverage_{'cuda' if device.is_cuda else 'cpu'}.json"
    write_json(out, {"machine": describe_device(device), "scenes": rows})


if __name__ == "__main__":
    main()
