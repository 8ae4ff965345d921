"""Scenes from files, TOML text and built-in names; bad scenes are ValueErrors with the
CLI's message; scenes pickle exactly."""

import os
import pathlib
import pickle
import subprocess

import pytest

import diffluid

ROOT = pathlib.Path(__file__).resolve().parents[2]


def test_builtin_names_load():
    names = diffluid.Scene.builtin_names()
    assert "block_drop" in names and "gradcheck_box" in names
    s = diffluid.Scene.builtin("block_drop")
    assert s.name == "block_drop" and s.steps == 50 and s.dt == 0.005
    assert s.body_names == ["block"] and s.size == [3.5, 1.5, 2.0]


def test_load_resolves_paths_and_builtin_names_like_the_cli():
    by_name = diffluid.Scene.load("block_drop")
    by_path = diffluid.Scene.load(str(ROOT / "assets/scenes/block_drop.toml"))
    assert by_name.to_json() == by_path.to_json()
    with pytest.raises(FileNotFoundError, match="no_such_scene"):
        diffluid.Scene.load("no_such_scene")


def test_from_toml_and_from_file_agree(tmp_path, small_toml):
    p = tmp_path / "small.toml"
    p.write_text(small_toml)
    a = diffluid.Scene.from_file(p)
    b = diffluid.Scene.from_toml(small_toml, base_dir=str(tmp_path))
    assert a == b
    assert a.body_names == ["ball"] and a.steps == 3


def test_unknown_builtin_is_a_value_error():
    with pytest.raises(ValueError, match='no built-in scene named "nope"'):
        diffluid.Scene.builtin("nope")


@pytest.mark.parametrize(
    "edit, message",
    [
        (("dx = 0.05", "dx = -0.05"), "domain.dx"),
        (("steps = 3", "steps = 0"), "time.steps: must be at least 1"),
        (("density = 500.0", "density = 500.0\nfoo = 1"), "unknown field `foo`"),
        (("radius = 0.06", "radius = nan"), "body[0]"),
        (("[0.2, 0.22, 0.2]", "[0.2, 0.22, 9.0]"), "body[0]"),
        (("name = \"small\"", "name = "), "line 2"),
    ],
)
def test_bad_scenes_are_value_errors(small_toml, edit, message):
    text = small_toml.replace(*edit)
    assert text != small_toml
    with pytest.raises(ValueError) as e:
        diffluid.Scene.from_toml(text, origin="bad.toml")
    assert message in str(e.value)
    assert str(e.value).startswith("scene bad.toml: ")


def test_missing_file_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="cannot read scene file"):
        diffluid.Scene.from_file(tmp_path / "missing.toml")


@pytest.mark.parametrize("special", ["/dev/zero", "fifo"])
def test_mesh_paths_that_are_not_regular_files_are_refused(tmp_path, small_toml, special):
    """A body's mesh that is /dev/zero used to be read until memory ran out, and a FIFO
    with no writer waited for ever, also through Scene.from_json (issue 39): both are
    refused as not regular files."""
    if special == "fifo":
        special = str(tmp_path / "mesh.obj")
        os.mkfifo(special)
    cube = str(ROOT / "assets" / "meshes" / "cube.obj")
    ball = 'shape = { kind = "ball", radius = 0.06 }'
    assert ball in small_toml
    text = small_toml.replace(ball, f'shape = {{ kind = "mesh", obj = "{cube}", scale = 0.5 }}')
    good = diffluid.Scene.from_toml(text, origin="mesh.toml").to_json()
    assert cube in good
    with pytest.raises(ValueError, match="not a regular file"):
        diffluid.Scene.from_json(good.replace(cube, special))
    with pytest.raises(ValueError, match="not a regular file"):
        diffluid.Scene.from_toml(text.replace(cube, special), origin="mesh.toml")


CLI = os.environ.get("DIFFLUID_CLI")


@pytest.mark.skipif(not CLI, reason="set DIFFLUID_CLI to the diffluid binary (python/ci.sh does)")
def test_messages_are_the_clis(tmp_path, small_toml):
    """The exception's message is the line the CLI prints after 'error: '."""
    p = tmp_path / "bad.toml"
    p.write_text(small_toml.replace("dx = 0.05", "dx = 0.0"))
    out = subprocess.run([CLI, "run", str(p), "--out", str(tmp_path / "o"), "--quiet"],
                         capture_output=True, text=True)
    assert out.returncode != 0
    line = [l for l in out.stderr.splitlines() if l.startswith("error: ")][-1]
    with pytest.raises(ValueError) as e:
        diffluid.Scene.from_file(p)
    assert line == "error: " + str(e.value)


def test_settable_steps_and_surface(box_scene):
    box_scene.steps = 2
    assert box_scene.steps == 2
    with pytest.raises(ValueError):
        box_scene.steps = 0
    assert box_scene.freeze_surface
    box_scene.freeze_surface = False
    assert not box_scene.freeze_surface


def test_scenes_pickle_exactly():
    s = diffluid.Scene.builtin("gradcheck_box")
    s.steps = 7
    t = pickle.loads(pickle.dumps(s))
    assert t == s and t.steps == 7 and t.to_json() == s.to_json()
    # The copy runs the same simulation bit for bit.
    a, b = diffluid.Simulation(s), diffluid.Simulation(t)
    a.run(2)
    b.run(2)
    assert (a.positions == b.positions).all()


def test_loss_and_optimize_spec():
    s = diffluid.Scene.builtin("block_drop")
    loss = s.loss
    assert loss.body == 0 and loss.position == ([1.45, 0.3, 1.3], 1.0)
    assert loss.orientation is None and loss.velocity is None
    spec = s.optimize_spec
    assert spec["params"] == ["v", "w"] and spec["optimizer"]["kind"] == "gd"
    assert spec["epochs"] == 50 and spec["freeze_surface"] is True
    assert diffluid.Scene.builtin("still_water").loss is None


def test_world_builder_builds_the_scene_files_world(small_toml):
    """The same world from code and from TOML: the same simulation, bit for bit."""
    built = (diffluid.WorldBuilder([0.4, 0.4, 0.4], 0.05, dt=0.01, steps=3, name="small",
                                   solver={"tolerance": 1e-10})
             .liquid({"kind": "box", "min": [0, 0, 0], "max": [0.4, 0.2, 0.4]})
             .body("ball", {"kind": "ball", "radius": 0.06}, position=[0.2, 0.22, 0.2],
                   density=500.0)
             .build())
    read = diffluid.Simulation(diffluid.Scene.from_toml(small_toml))
    built.run()
    read.run()
    assert (built.positions == read.positions).all() and (built.pressure == read.pressure).all()


def test_world_builder_errors_name_the_key():
    b = diffluid.WorldBuilder([0.4, 0.4, 0.4], 0.05)
    b.body("ball", {"kind": "ball", "radius": -1.0}, position=[0.2, 0.2, 0.2], density=500.0)
    with pytest.raises(ValueError, match=r"body\[0\].*ball radius must be a positive number"):
        b.build()
    with pytest.raises(ValueError, match="unknown field `tolerence`"):
        diffluid.WorldBuilder([0.4, 0.4, 0.4], 0.05, solver={"tolerence": 1e-9}).build()
