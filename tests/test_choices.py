"""Each closed choice and default is defined once (dynmesh_warp.choices; issue 13): the scene
schema, the CLIs' help, the kernels' constants and the Newton adapter derive from it."""

from __future__ import annotations

import contextlib
import inspect
import io

import pytest

from dynmesh_warp import choices as C
from dynmesh_warp.config import (
    DEFAULT_SCENE,
    DEFAULT_SCENE_FILE,
    ConversionConfig,
    GaussiansConfig,
    NewtonConfig,
    PhysicsConfig,
    PhysicsCore,
    SceneError,
    SurfaceConfig,
    load_scene_config,
)

# (schema model, field) -> (enum, default) of dynmesh_warp.choices
SCHEMA = [
    (PhysicsConfig, "collider", C.Collider, C.DEFAULT_COLLIDER),
    (PhysicsConfig, "rebuild_every", C.RebuildEvery, C.DEFAULT_REBUILD_EVERY),
    (SurfaceConfig, "playback", C.Playback, C.DEFAULT_PLAYBACK),
    (SurfaceConfig, "frame_order", C.FrameOrder, C.DEFAULT_FRAME_ORDER),
    (SurfaceConfig, "orientation", C.Orientation, C.DEFAULT_ORIENTATION),
    (SurfaceConfig, "up_axis", C.UpAxis, C.DEFAULT_UP_AXIS),
    (ConversionConfig, "strategy", C.Strategy, C.DEFAULT_STRATEGY),
    (NewtonConfig, "solver", C.NewtonSolver, C.DEFAULT_NEWTON_SOLVER),
    (GaussiansConfig, "colors", C.ColorSource, C.DEFAULT_COLOR_SOURCE),
]


def _help(main) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        main(["--help"])
    return " ".join(out.getvalue().split())


def _braces(choice) -> str:
    return "{" + ",".join(C.values(choice)) + "}"


@pytest.mark.parametrize("model, field, choice, default", SCHEMA, ids=[f"{m.__name__}.{f}" for m, f, *_ in SCHEMA])
def test_schema_fields_are_the_enums(model, field, choice, default):
    info = model.model_fields[field]
    assert info.annotation is choice and info.default is default
    schema = model.model_json_schema()
    enum_def = schema["$defs"][choice.__name__] if "$defs" in schema else schema["properties"][field]
    assert enum_def["enum"] == C.values(choice)


def test_enum_members_are_their_strings():
    assert C.Collider.SWEPT == "swept" and f"{C.Collider.SWEPT}" == "swept" and str(C.Strategy.GRAPH) == "graph"
    assert C.STRATEGIES == tuple(C.values(C.Strategy))
    with pytest.raises(ValueError, match=r"collider must be one of \['fixed', 'refit', 'swept', 'rebuild'\]"):
        C.parse(C.Collider, "bvh", "collider")


def test_a_bad_choice_in_a_scene_names_the_field_and_the_values():
    with pytest.raises(SceneError, match=r"physics\.collider.*'fixed', 'refit', 'swept' or 'rebuild'"):
        load_scene_config(data={"physics": {"collider": "bvh"}})
    cfg = load_scene_config(data={"physics": {"collider": "swept"}, "surface": {"playback": "pingpong"}})
    assert cfg.physics.collider is C.Collider.SWEPT and cfg.surface.playback == "pingpong"


def test_cli_help_derives_from_the_enums():
    from dynmesh_warp.convert import main as convert_main
    from dynmesh_warp.evaluate import main as evaluate_main
    from dynmesh_warp.run import _parser

    run_help = " ".join(_parser().format_help().split())
    assert _braces(C.Collider) in run_help and _braces(C.RebuildEvery) in run_help
    assert f"{C.DEFAULT_COLLIDER} (default)" in run_help
    conv = _help(convert_main)
    assert _braces(C.Strategy) in conv and f"default {C.DEFAULT_STRATEGY}" in conv
    ev = _help(evaluate_main)
    assert _braces(C.FrameOrder) in ev
    from dynmesh_warp.render import main as render_main

    ren = _help(render_main)
    assert _braces(C.Rasteriser) in ren and f"{C.DEFAULT_RASTERISER['cuda']} on CUDA" in ren


def test_kernels_and_world_take_the_codes_from_the_enum():
    from dynmesh_warp.kernels import frames
    from dynmesh_warp.world import COLLIDER_CHOICES, PLAYBACK_MODES, World

    coded = [m for m in C.Playback if m != C.Playback.AUTO]  # auto is resolved on the sequence first
    assert {m: int(getattr(frames, f"PLAYBACK_{m.name}")) for m in coded} == C.PLAYBACK_CODES
    assert PLAYBACK_MODES == {m.value: c for m, c in C.PLAYBACK_CODES.items()}
    assert COLLIDER_CHOICES == tuple(C.values(C.Collider))
    sig = inspect.signature(World.__init__).parameters
    assert sig["collider"].default is C.DEFAULT_COLLIDER and sig["rebuild_every"].default is C.DEFAULT_REBUILD_EVERY


def test_newton_adapter_defaults_are_the_physics_defaults():
    from dynmesh_warp import newton_adapter as na

    assert na.SOLVERS == tuple(C.values(C.NewtonSolver))
    assert inspect.signature(na.make_solver).parameters["name"].default is C.DEFAULT_NEWTON_SOLVER
    core = {k: f.default for k, f in PhysicsCore.model_fields.items()}
    for cls in (na.DeformingMeshShape, na.NewtonWorld):
        sig = inspect.signature(cls.__init__).parameters
        assert sig["mu"].default == core["friction"] and sig["restitution"].default == core["restitution"]
    sig = inspect.signature(na.NewtonWorld.__init__).parameters
    assert sig["dt"].default == core["dt"] and sig["substeps"].default == core["substeps"]
    assert sig["solver"].default is C.DEFAULT_NEWTON_SOLVER


def test_the_default_scene_is_the_packaged_yaml():
    assert DEFAULT_SCENE_FILE.is_file() and DEFAULT_SCENE_FILE.parent.name == "dynmesh_warp"
    a = load_scene_config()
    b = load_scene_config(DEFAULT_SCENE_FILE)
    assert a.model_dump() == b.model_dump() and a.name == "default" == DEFAULT_SCENE["name"]
    # it restates no physics default: the schema is the one home of those
    assert "physics" not in DEFAULT_SCENE
    assert a.physics.model_dump() == PhysicsConfig().model_dump()
