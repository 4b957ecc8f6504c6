"""The object catalogue: TOML and JSON round trips, models with declared mass/density/symmetries, BOP models_info
export and import, scenes naming catalogue parts, `sygrid parts PATH`, and errors that name the file, part and
field. CAD fixtures are made here with trimesh (millimetres): a closed plate, an open tube, two components."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from launch.cli import main
from sygrid.catalogue import load_catalogue, open_parts, parse_catalogue, write_catalogue
from sygrid.catalogue_bop import catalogue_from_bop_models, export_bop_models
from sygrid.drop import resolve_objects
from sygrid.errors import ConfigError
from sygrid.objects import builtin_part
from sygrid.objects.cad import MATERIAL_DENSITY_KG_M3
from sygrid.scene import default_scene, parse_scene, scene_to_json

FLIP_X = [1.0, 0, 0, 0, 0, -1.0, 0, 0, 0, 0, -1.0, 0, 0, 0, 0, 1.0]


@pytest.fixture()
def cad(tmp_path: Path) -> Path:
    """tmp_path/cad: plate.stl (closed, off the origin), tube.ply (open), pair.obj (two components); in mm."""
    folder = tmp_path / "cad"
    folder.mkdir()
    plate = trimesh.creation.box((40.0, 20.0, 4.0))
    plate.apply_translation((0.0, 0.0, 2.0))  # its flip about x runs through z = 2 mm
    plate.export(folder / "plate.stl")
    tube = trimesh.creation.annulus(4.0, 10.0, 30.0, sections=48)
    tube.update_faces(np.abs(tube.face_normals[:, 2]) < 0.5)  # no end faces: open
    tube.remove_unreferenced_vertices()
    tube.export(folder / "tube.ply")
    a = trimesh.creation.cylinder(5.0, 30.0, sections=32)
    b = trimesh.creation.box((10.0, 10.0, 10.0))
    b.apply_translation((20.0, 0.0, 0.0))
    trimesh.util.concatenate([a, b]).export(folder / "pair.obj")
    return folder


CATALOGUE_TOML = """
[[part]]
id = 11
name = "plate"
file = "cad/plate.stl"
unit = "mm"
material = "aluminium"
symmetries_discrete = [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0.004, 0, 0, 0, 1]]

[part.grasp]
max_opening_m = 0.05
approach_axis = [0, 0, -2]

[[part]]
id = 12
name = "tube"
file = "cad/tube.ply"
unit = "mm"
mass_kg = 0.02
symmetries_continuous = [{axis = [0, 0, 1], offset_m = [0, 0, 0]}]

[[part]]
id = 13
name = "pair"
file = "cad/pair.obj"
unit = "mm"
density_kg_m3 = 1000.0

[[part]]
id = 14
name = "nut"
builtin = "hex_nut"
material = "brass"
"""


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_toml_round_trip_and_json(cad: Path, tmp_path: Path) -> None:
    catalogue = load_catalogue(_write(tmp_path / "parts.toml", CATALOGUE_TOML))
    assert catalogue.names == ("plate", "tube", "pair", "nut")
    for suffix in (".toml", ".json"):
        out = write_catalogue(catalogue, tmp_path / "elsewhere" / f"copy{suffix}")
        again = load_catalogue(out)
        assert again.names == catalogue.names
        for a, b in zip(catalogue.parts, again.parts, strict=True):
            assert a.model_dump(exclude={"file"}) == b.model_dump(exclude={"file"})
            if a.file is not None:
                assert (again.base_dir / b.file).resolve() == (catalogue.base_dir / a.file).resolve()
                assert b.file.startswith("../cad/")  # relative to the written file
    data = json.loads((tmp_path / "elsewhere" / "copy.json").read_text())
    assert [p["id"] for p in data["part"]] == [11, 12, 13, 14]


def test_models_carry_the_declarations(cad: Path, tmp_path: Path) -> None:
    plate, tube, pair, nut = load_catalogue(_write(tmp_path / "parts.toml", CATALOGUE_TOML)).models()
    assert [m.obj_id for m in (plate, tube, pair, nut)] == [11, 12, 13, 14]
    assert plate.material == "aluminium" and plate.density_kg_m3 == MATERIAL_DENSITY_KG_M3["aluminium"]
    np.testing.assert_allclose(plate.symmetries_discrete[0][1, 3], 0.0)
    np.testing.assert_allclose(plate.symmetries_discrete[0][2, 3], 0.004)
    assert plate.metadata["symmetry_problems"] == []  # the flip through z = 2 mm holds
    assert plate.metadata["grasp"] == {"max_opening_m": 0.05, "approach_axis": [0.0, 0.0, -1.0]}
    assert plate.mass_source == "density x solid volume"
    assert plate.mass_kg == pytest.approx(40e-3 * 20e-3 * 4e-3 * 2700.0)
    assert tube.mass_kg == pytest.approx(0.02) and tube.mass_source == "declared"  # open, yet as declared
    assert not tube.mesh.is_watertight
    assert pair.mass_kg == pytest.approx(pair.volume_m3 * 1000.0) and pair.mesh.body_count == 2
    builtin = builtin_part("hex_nut")
    assert nut.name == "nut" and nut.material == "brass" and nut.density_kg_m3 == MATERIAL_DENSITY_KG_M3["brass"]
    assert nut.symmetries_discrete == builtin.symmetries_discrete and builtin.obj_id == 1  # the cache is untouched


def test_bop_models_export_and_import(cad: Path, tmp_path: Path) -> None:
    catalogue = load_catalogue(_write(tmp_path / "parts.toml", CATALOGUE_TOML))
    export_bop_models(catalogue, tmp_path / "bop")
    info = json.loads((tmp_path / "bop" / "models" / "models_info.json").read_text())
    assert sorted(info, key=int) == ["11", "12", "13", "14"]
    plate = catalogue.model("plate")
    assert info["11"]["diameter"] == pytest.approx(plate.diameter_m * 1000.0)
    assert info["11"]["symmetries_discrete"][0][11] == pytest.approx(4.0)  # millimetres in the file
    assert info["12"]["symmetries_continuous"] == [{"axis": [0.0, 0.0, 1.0], "offset": [0.0, 0.0, 0.0]}]

    imported = catalogue_from_bop_models(tmp_path / "bop" / "models", tmp_path, names={11: "plate", 12: "tube"})
    assert [p.id for p in imported.parts] == [11, 12, 13, 14]
    assert imported.names == ("plate", "tube", "obj_000013", "obj_000014")
    assert imported.parts[0].file == "bop/models/obj_000011.ply" and imported.parts[0].unit == "mm"
    np.testing.assert_allclose(imported.parts[0].symmetries_discrete[0], plate.symmetries_discrete[0].reshape(-1))
    nut = imported.model("obj_000014")
    assert len(nut.symmetries_discrete) == 11 and nut.metadata["symmetry_problems"] == []
    for a, b in zip(catalogue.models(), imported.models(), strict=True):
        assert b.diameter_m == pytest.approx(a.diameter_m, rel=1e-6)


def test_bop_import_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"models_info\.json: missing"):
        catalogue_from_bop_models(tmp_path)
    (tmp_path / "models_info.json").write_text(json.dumps({"3": {"symmetries_discrete": [[1, 0, 0]]}}))
    with pytest.raises(ConfigError, match=r"models_info.json\[3\].symmetries_discrete\[0\]: expected 16 numbers"):
        catalogue_from_bop_models(tmp_path)


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (
            ('id = 12\nname = "tube"', 'id = 11\nname = "tube"'),
            r"part: id values must be unique, repeated: 11 in part\[0\] \(plate\), part\[1\] \(tube\)$",
        ),
        (
            ('name = "tube"', 'name = "plate"'),
            r"part: name values must be unique, repeated: 'plate' in part\[0\] \(plate\), part\[1\] \(plate\)$",
        ),
        (('unit = "mm"\nmass_kg', "mass_kg"), r"part\[1\] \(tube\): 'unit' is required with 'file'"),
        (('material = "aluminium"', 'material = "unobtainium"'), r"part\[0\] \(plate\)\.material: must be one of"),
        (("cad/pair.obj", "cad/missing.obj"), r"part\[2\] \(pair\)\.file: no such file 'cad/missing.obj'"),
        (("cad/pair.obj", "cad/pair.step"), r"part\[2\] \(pair\): file: must be a \.ply, \.obj, \.stl mesh"),
        (("id = 13", "id = true"), r"part\[2\] \(pair\)\.id: "),
        (("id = 13", "id = 0"), r"part\[2\] \(pair\)\.id: must be >= 1, got 0"),
        (("density_kg_m3 = 1000.0", "density_kg_m3 = 1000.0\nmass_kg = 0.1"), r"give 'mass_kg' or 'density_kg_m3'"),
        (('builtin = "hex_nut"', 'builtin = "hex_nutt"'), r"builtin: unknown part 'hex_nutt'; valid: hex_nut"),
        (('builtin = "hex_nut"', 'builtin = "hex_nut"\nfile = "cad/pair.obj"'), r"exactly one of 'file'"),
        (("max_opening_m = 0.05", "max_openning_m = 0.05"), r"part\[0\] \(plate\)\.grasp\.max_openning_m: unknown key"),
        (("approach_axis = [0, 0, -2]", "approach_cone_deg = 30.0"), r"'approach_cone_deg' needs 'approach_axis'"),
        (("[0, 0, 1], offset_m", "[0, 0, 0], offset_m"), r"symmetries_continuous\[0\]\.axis: must be a non-zero"),
        (("0, 0, 0, 1]]", "0, 0, 0]]"), r"symmetries_discrete: \[0\] must be a 4x4 transform as 16 numbers"),
        (("mass_kg = 0.02", "mass_kg = nan"), r"part\[1\] \(tube\)\.mass_kg: "),
        (("[[part]]\nid = 11", "[[part]\nid = 11"), r"not valid TOML"),
    ],
)
def test_errors_name_the_file_part_and_field(cad: Path, tmp_path: Path, edit: tuple[str, str], expected: str) -> None:
    old, new = edit
    assert old in CATALOGUE_TOML
    path = _write(tmp_path / "parts.toml", CATALOGUE_TOML.replace(old, new, 1))
    with pytest.raises(ConfigError, match=expected) as info:
        load_catalogue(path)
    assert str(info.value).startswith(str(path))


def test_empty_and_wrong_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"part: must have at least 1 item"):
        parse_catalogue({"part": []}, "c.json", tmp_path)
    with pytest.raises(ConfigError, match=r"c.json: shapes: unknown key"):
        parse_catalogue({"part": [{"id": 1, "name": "a", "builtin": "washer"}], "shapes": []}, "c.json", tmp_path)
    with pytest.raises(ConfigError, match=r"parts.yaml: a catalogue must be a .toml or .json file"):
        load_catalogue(tmp_path / "parts.yaml")
    with pytest.raises(ConfigError, match=r"parts.toml: cannot read the catalogue"):
        load_catalogue(tmp_path / "parts.toml")
    catalogue = parse_catalogue({"part": [{"id": 1, "name": "a", "builtin": "washer"}]}, "c.json", tmp_path)
    with pytest.raises(ConfigError, match=r"c.json: no part named 'b'; its parts: a"):
        catalogue.model("b")


def test_scenes_name_catalogue_parts(cad: Path, tmp_path: Path) -> None:
    _write(tmp_path / "parts.toml", CATALOGUE_TOML)
    scene = parse_scene(
        {"catalogue": "parts.toml", "objects": [{"catalogue_part": "pair", "count": 5}, {"builtin": "washer"}]}
    )
    pair, washer = resolve_objects(scene, tmp_path)
    assert (pair.obj_id, pair.name, washer.obj_id) == (13, "pair", 3)
    assert scene.objects[0].label == "pair" and scene_to_json(scene)["catalogue"] == "parts.toml"

    unknown = parse_scene({"catalogue": "parts.toml", "objects": [{"catalogue_part": "paire"}]})
    with pytest.raises(ConfigError, match=r"objects\[0\]: .*parts.toml: no part named 'paire'; its parts: plate"):
        resolve_objects(unknown, tmp_path)
    clash = parse_scene(
        {"catalogue": "parts.toml", "objects": [{"builtin": "pipe", "obj_id": 12}, {"catalogue_part": "tube"}]}
    )
    with pytest.raises(ConfigError, match=r"objects\[1\] \(tube\) has obj_id 12, already taken by 'pipe'"):
        resolve_objects(clash, tmp_path)
    with pytest.raises(ConfigError, match=r"objects\[0\] name\(s\) a 'catalogue_part': give the scene's 'catalogue'"):
        parse_scene({"objects": [{"catalogue_part": "pair"}]})
    with pytest.raises(ConfigError, match=r"objects\[0\]: a 'catalogue_part' takes only 'count': its obj_id"):
        parse_scene({"catalogue": "parts.toml", "objects": [{"catalogue_part": "pair", "obj_id": 4}]})
    with pytest.raises(ConfigError, match=r"objects\[0\]: give exactly one of 'builtin'"):
        parse_scene({"catalogue": "parts.toml", "objects": [{"catalogue_part": "pair", "builtin": "washer"}]})


def test_scenes_without_a_catalogue_keep_their_json() -> None:
    data = scene_to_json(default_scene())
    assert "catalogue" not in data and all("catalogue_part" not in o for o in data["objects"])


def test_a_folder_of_cad_files(cad: Path) -> None:
    catalogue = open_parts(cad, "mm", first_id=20)
    assert [(p.id, p.name, p.file) for p in catalogue.parts] == [
        (20, "pair", "pair.obj"),
        (21, "plate", "plate.stl"),
        (22, "tube", "tube.ply"),
    ]
    assert open_parts(cad / "tube.ply", "m").parts[0].unit == "m"
    with pytest.raises(ConfigError, match=r"--unit is required with CAD files"):
        open_parts(cad)
    (cad / "tube.stl").write_bytes((cad / "plate.stl").read_bytes())
    with pytest.raises(ConfigError, match=r"files share a name \(their stem\): \['tube'\]"):
        open_parts(cad, "mm")
    with pytest.raises(ConfigError, match=r"expected a catalogue"):
        open_parts(cad / "notes.txt", "mm")


def test_sygrid_parts_on_a_folder_writes_a_catalogue(cad: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "proposed.toml"
    assert main(["parts", str(cad), "--unit", "mm", "--write-catalogue", str(out)]) == 0
    text = capsys.readouterr().out
    assert "2 component(s)" in text and "OPEN (not watertight)" in text
    assert "density x repaired solid volume" in text and "warning: open mesh" in text
    assert "symmetries proposed: 1 discrete + 1 continuous: continuous about (0, 0, 1)" in text  # the tube
    written = load_catalogue(out)
    assert written.names == ("pair", "plate", "tube")
    plate = written.part("plate")
    assert len(plate.symmetries_discrete) == 3  # D2 of a box, through its centre at z = 2 mm
    flip_x = next(T for T in plate.symmetries_discrete if T[0] == 1.0)
    assert flip_x[11] == pytest.approx(0.004)
    assert written.part("tube").symmetries_continuous[0].axis == (0.0, 0.0, 1.0)
    assert written.model("plate").metadata["symmetry_problems"] == []

    assert main(["parts", str(out)]) == 0
    assert "(matches the declared)" in capsys.readouterr().out
    mesh_out = tmp_path / "plate_m.stl"
    assert main(["parts", str(out), "--export", "plate", "--out", str(mesh_out), "--unit", "m"]) == 0
    assert trimesh.load(mesh_out).extents.max() == pytest.approx(0.04)
    assert main(["parts", str(out), "--export", "nope", "--out", str(mesh_out)]) == 2
    assert "no part named 'nope'" in capsys.readouterr().err


def test_sygrid_parts_lists_the_builtins(capsys) -> None:
    assert main(["parts"]) == 0
    text = capsys.readouterr().out
    assert "hex_nut" in text and "flange" in text
    assert main(["parts", "--write-catalogue", "x.toml"]) == 2
