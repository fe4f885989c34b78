"""Warp kernels of dynmesh_warp, grouped by pipeline stage.

- :mod:`.frames`    — per-step surface state from the frame buffer (copy / interpolation).
- :mod:`.geometry`  — face normals, closest point on a triangle, batched NearestSurface.
- :mod:`.collide`   — sphere–mesh contact generation (BVH refit path and swept-bounds path).
- :mod:`.integrate` — sphere dynamics with contact response.

Host code launches these through thin wrappers in ``dynmesh_warp``; kernels allocate nothing.
"""
