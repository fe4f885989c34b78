"""Newton adapter stage: collision bounds of the deforming mesh shape for Newton's broad phase.

Newton's ``CollisionPipeline`` bounds a mesh shape by a local AABB
(``Model.shape_collision_aabb_lower/upper``) and a bounding radius
(``Model.shape_collision_radius``) computed once at ``ModelBuilder.finalize``. A deforming mesh
leaves those bounds, so they are recomputed from the current vertices every sub-step, on the
device (no host read, capturable in a CUDA graph): one thread resets the entry, then one thread
per vertex folds its point in with atomic min/max.
"""

import warp as wp


@wp.kernel
def reset_shape_bounds(
    # In:
    shape: int,
    # Out:
    aabb_lower: wp.array[wp.vec3],
    aabb_upper: wp.array[wp.vec3],
    radius: wp.array[float],
):
    """Set shape ``shape``'s local AABB to empty (+inf, -inf) and its bounding radius to 0.

    aabb_lower, aabb_upper (num_shapes,) [m]; radius (num_shapes,) [m]. Launch with dim 1.
    """
    big = 1.0e30
    aabb_lower[shape] = wp.vec3(big, big, big)
    aabb_upper[shape] = wp.vec3(-big, -big, -big)
    radius[shape] = 0.0


@wp.kernel
def accumulate_shape_bounds(
    # In:
    points: wp.array[wp.vec3],
    shape: int,
    pad: float,
    # Out (accumulated):
    aabb_lower: wp.array[wp.vec3],
    aabb_upper: wp.array[wp.vec3],
    radius: wp.array[float],
):
    """Grow shape ``shape``'s local AABB and bounding radius to contain every point.

    points (N,) mesh vertices in the shape's local frame [m]; pad [m] is added on every side
    (and to the radius) to cover motion between bound updates; aabb_lower, aabb_upper
    (num_shapes,) [m]; radius (num_shapes,) [m] = max |point| + pad. Launch with dim N after
    :func:`reset_shape_bounds`.
    """
    i = wp.tid()
    p = points[i]
    d = wp.vec3(pad, pad, pad)
    wp.atomic_min(aabb_lower, shape, p - d)
    wp.atomic_max(aabb_upper, shape, p + d)
    wp.atomic_max(radius, shape, wp.length(p) + pad)
