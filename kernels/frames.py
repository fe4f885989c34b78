"""Stage 1: surface vertices for the current time from the per-frame vertex buffer."""

import warp as wp

from ..choices import PLAYBACK_CODES, Playback

# Playback modes for times past the last frame (codes of dynmesh_warp.choices.Playback).
PLAYBACK_LOOP = wp.constant(PLAYBACK_CODES[Playback.LOOP])
PLAYBACK_CLAMP = wp.constant(PLAYBACK_CODES[Playback.CLAMP])
PLAYBACK_PINGPONG = wp.constant(PLAYBACK_CODES[Playback.PINGPONG])


@wp.func
def wrap_frame(k: int, num_frames: int, mode: int) -> int:
    """Map an unbounded frame number to [0, num_frames) for a playback mode."""
    if num_frames <= 1:
        return 0
    if mode == PLAYBACK_CLAMP:
        return wp.clamp(k, 0, num_frames - 1)
    if mode == PLAYBACK_PINGPONG:
        period = 2 * (num_frames - 1)
        m = k % period
        if m < 0:
            m += period
        if m >= num_frames:
            m = period - m
        return m
    m = k % num_frames
    if m < 0:
        m += num_frames
    return m


#: a clock within this many frames below a frame boundary is on it [frames]. The clock adds dt
#: each step, so a step meant to start at k / fps often starts a few ulps before it; without the
#: snap that step took the pair (k-1, k) at alpha ~ 1 and so the previous interval's velocity for
#: the whole step (a new user's zig-zag plane: the wrong sign on 16 of 24 boundary steps; a
#: turntable at one step a frame: the resting sphere crept outwards 2 % in 1.7 s)
FRAME_SNAP = 1.0e-6
FRAME_SNAP_WP = wp.constant(wp.float64(FRAME_SNAP))


@wp.func
def frame_pair(time: wp.float64, fps: wp.float64, num_frames: int, mode: int):
    """Frames (k, k+1) bracketing ``time`` and the blend factor alpha in [0, 1).

    k = floor(time * fps) in float64, or the next frame when time * fps is within
    ``FRAME_SNAP`` below it (the clock's rounding); the same IEEE arithmetic as the host's
    ``frame_pair_host``, so host and device agree on every frame boundary.
    """
    s = time * fps
    kf = wp.floor(s)
    if s - kf > wp.float64(1.0) - FRAME_SNAP_WP:
        kf = kf + wp.float64(1.0)
    alpha = float(wp.max(s - kf, wp.float64(0.0)))
    k = int(kf)
    return wrap_frame(k, num_frames, mode), wrap_frame(k + 1, num_frames, mode), alpha


@wp.func
def blend_pair(time: wp.float64, fps: wp.float64, num_frames: int, mode: int, interpolate: int):
    """``frame_pair`` with alpha forced to 0 when interpolation is off (frame k is held)."""
    k0, k1, alpha = frame_pair(time, fps, num_frames, mode)
    if interpolate == 0:
        alpha = 0.0
    return k0, k1, alpha


@wp.func
def store_frame_key(
    time: wp.float64,
    fps: wp.float64,
    num_frames: int,
    mode: int,
    frame_key_out: wp.array[wp.int32],
    frame_changed_out: wp.array[wp.int32],
):
    """The clock's frame pair at ``time`` into State: frame_key_out[0] = k0 * num_frames + k1,
    frame_changed_out[0] = 1 if that differs from the stored key, else 0 (one thread)."""
    k0, k1, alpha = frame_pair(time, fps, num_frames, mode)
    key = k0 * num_frames + k1
    if key != frame_key_out[0]:
        frame_key_out[0] = key
        frame_changed_out[0] = 1
    else:
        frame_changed_out[0] = 0


@wp.kernel
def update_frame_vertices(
    # Model:
    frames: wp.array2d[wp.vec3],
    # State in:
    sim_time_in: wp.array[wp.float64],
    # In:
    fps: wp.float64,
    mode: int,
    interpolate: int,
    # State out:
    points_out: wp.array[wp.vec3],
    velocities_out: wp.array[wp.vec3],
):
    """Write the surface vertices and velocities_out at ``sim_time_in[0]``.

    frames (T, N) vertex buffer [m]; points_out (N,) [m]; velocities_out (N,) [m/s].
    With ``interpolate`` the position is the linear blend of frames k and k+1; otherwise
    frame k is copied. The velocity is the finite difference (V[k+1] - V[k]) * fps in
    both cases (the surface's own motion, used by the contact response).
    """
    i = wp.tid()
    num_frames = frames.shape[0]
    k0, k1, alpha = frame_pair(sim_time_in[0], fps, num_frames, mode)
    a = frames[k0, i]
    b = frames[k1, i]
    if interpolate != 0:
        points_out[i] = a + alpha * (b - a)
    else:
        points_out[i] = a
    if k1 == k0:
        velocities_out[i] = wp.vec3(0.0)
    else:
        velocities_out[i] = (b - a) * float(fps)


@wp.kernel
def blend_segment_vertices(
    # Model:
    frames: wp.array2d[wp.vec3],
    # In:
    k0: int,
    k1: int,
    alpha: float,
    fps: float,
    # State out:
    points_out: wp.array[wp.vec3],
    velocities_out: wp.array[wp.vec3],
):
    """One segment of a piecewise-fixed surface at a time the host resolved: points_out (N,) [m]
    = frames[k0] + alpha (frames[k1] - frames[k0]); velocities_out (N,) [m/s] = (frames[k1] -
    frames[k0]) * fps, zero when k1 == k0 (a held frame). frames (T_s, N) [m], k0 / k1 indices
    within the segment, alpha in [0, 1), fps [1/s]."""
    i = wp.tid()
    a = frames[k0, i]
    b = frames[k1, i]
    points_out[i] = a + alpha * (b - a)
    if k1 == k0:
        velocities_out[i] = wp.vec3(0.0)
    else:
        velocities_out[i] = (b - a) * fps


@wp.kernel
def add_points_offset(
    # In:
    points: wp.array[wp.vec3],
    offset: wp.vec3,
    # Out:
    points_out: wp.array[wp.vec3],
):
    """points_out = points + offset (N,) [m] (a copy of a surface drawn elsewhere, e.g. one tile
    of the viewer's env grid)."""
    i = wp.tid()
    points_out[i] = points[i] + offset
