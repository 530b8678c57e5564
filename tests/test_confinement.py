"""Every path a scene's files name stays inside the scene folder; names used in folder names are plain."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from dualnerf.io import InputError, PreprocessConfig, preprocess
from dualnerf.scenes import SceneSpecError, load_gt_edit, load_scene_spec
from pipeline.paths import PathError, check_plain_name, confined
from tests.test_preprocess import _transforms_case

ROOT = Path(__file__).resolve().parents[1]
ABLATION = ROOT / "workflows" / "ablation.toml"


# ---- transforms.json ---------------------------------------------------------------------------------

def _outside_image(tiny_scene, tmp_path) -> Path:
    outside = tmp_path / "outside.png"
    shutil.copyfile(tiny_scene / "images" / "view_000.png", outside)
    return outside


@pytest.mark.parametrize("kind", ["relative", "absolute"])
def test_transforms_file_path_leaving_the_folder_is_refused(tiny_scene, tmp_path, kind):
    outside = _outside_image(tiny_scene, tmp_path)
    value = "../outside.png" if kind == "relative" else str(outside)

    def mutate(doc):
        doc["frames"][0]["file_path"] = value
    folder = _transforms_case(tiny_scene, tmp_path, mutate)
    with pytest.raises(InputError) as err:
        preprocess(folder, tmp_path / "out", PreprocessConfig())
    message = str(err.value)
    assert "transforms.json" in message and "frame 0" in message and "file_path" in message
    assert repr(value) in message and "outside the scene folder" in message
    assert not (tmp_path / "out").exists()


def test_a_link_out_of_the_folder_is_refused(tiny_scene, tmp_path):
    outside = _outside_image(tiny_scene, tmp_path)
    folder = _transforms_case(tiny_scene, tmp_path, lambda doc: None)
    (folder / "images" / "view_003.png").unlink()
    os.symlink(outside, folder / "images" / "view_003.png")
    with pytest.raises(InputError, match=r"frame 3.*'images/view_003\.png'.*outside the scene folder"):
        preprocess(folder, tmp_path / "out", PreprocessConfig())


def test_ply_file_path_leaving_the_folder_is_refused(tiny_scene, tmp_path):
    shutil.copyfile(tiny_scene / "gt" / "sparse_pc.ply", tmp_path / "points.ply")
    folder = _transforms_case(tiny_scene, tmp_path, lambda doc: doc.update(ply_file_path="../points.ply"))
    with pytest.raises(InputError, match=r"ply_file_path '\.\./points\.ply'.*outside the scene folder"):
        preprocess(folder, tmp_path / "out", PreprocessConfig())


def test_links_inside_the_folder_are_followed(tiny_scene, tmp_path):
    folder = _transforms_case(tiny_scene, tmp_path, lambda doc: None)
    (folder / "images").rename(folder / "real")
    os.symlink("real", folder / "images")
    report = preprocess(folder, tmp_path / "out", PreprocessConfig())
    assert report["registered"] == 26


def test_procedural_ground_truth_cameras_outside_gt_are_inside_the_scene(tiny_scene, tmp_path):
    """gt/transforms.json names ../images/: inside the scene folder, so it is allowed."""
    report = preprocess(tiny_scene, tmp_path / "out", PreprocessConfig(method="nerfstudio"))
    assert report["registered"] == 26


# ---- image folders (SfM) and COLMAP models ------------------------------------------------------------

def test_image_folder_with_a_link_out_is_refused(tiny_scene, tmp_path):
    outside = _outside_image(tiny_scene, tmp_path)
    folder = tmp_path / "photos"
    folder.mkdir()
    for name in ("view_001.png", "view_002.png", "view_003.png"):
        shutil.copyfile(tiny_scene / "images" / name, folder / name)
    os.symlink(outside, folder / "view_000.png")
    with pytest.raises(InputError, match=r"image 'view_000\.png'.*outside the scene folder"):
        preprocess(folder, tmp_path / "out", PreprocessConfig(method="sfm"))


def _colmap_text_model(folder: Path, names: list[str]) -> None:
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text("1 PINHOLE 160 120 150 150 80 60\n")
    lines = [f"{i + 1} 1 0 0 0 {0.3 * i} 0 0 1 {name}\n\n" for i, name in enumerate(names)]
    (model / "images.txt").write_text("".join(lines))
    (model / "points3D.txt").write_text("")


def test_colmap_image_names_leaving_the_folder_are_refused(tiny_scene, tmp_path):
    (tmp_path / "elsewhere").mkdir()
    for i in range(3):
        shutil.copyfile(tiny_scene / "images" / f"view_00{i}.png", tmp_path / "elsewhere" / f"v{i}.png")
    folder = tmp_path / "model"
    (folder / "images").mkdir(parents=True)
    _colmap_text_model(folder, ["../../elsewhere/v0.png", "../../elsewhere/v1.png", "../../elsewhere/v2.png"])
    with pytest.raises(InputError) as err:
        preprocess(folder, tmp_path / "out", PreprocessConfig(method="colmap"))
    message = str(err.value)
    assert "COLMAP model image 1" in message and "image name '../../elsewhere/v0.png'" in message
    assert "outside the scene folder" in message


def test_colmap_model_whose_images_folder_is_outside_the_source_is_refused(tiny_scene, tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene / "images", scene / "images")
    _colmap_text_model(scene, ["view_000.png", "view_001.png", "view_002.png"])
    with pytest.raises(InputError, match=r"images folder .*outside the scene folder"):
        preprocess(scene / "sparse" / "0", tmp_path / "out", PreprocessConfig(method="colmap"))


# ---- scene.toml and ground-truth edits ---------------------------------------------------------------

@pytest.mark.parametrize("edit_id", ["../../escape", "a/b", "..", " snow"])
def test_scene_toml_edit_ids_must_be_plain_names(tmp_path, edit_id):
    (tmp_path / "scene.toml").write_text(
        f'[scene]\nname = "x"\n[[edits]]\nid = {json.dumps(edit_id)}\ninstruction = "i"\n'
        f'source_caption = "s"\ntarget_caption = "t"\n')
    with pytest.raises(SceneSpecError, match=r"scene\.toml: \[\[edits\]\] entry 1: id .* not a plain name.*letters"):
        load_scene_spec(tmp_path)


def test_scene_toml_scene_name_with_folders_is_refused(tmp_path):
    (tmp_path / "scene.toml").write_text('[scene]\nname = "../x"\n')
    with pytest.raises(SceneSpecError, match=r"\[scene\]: name '\.\./x'"):
        load_scene_spec(tmp_path)


def test_ground_truth_lookups_stay_inside_the_folder(tiny_scene, tmp_path):
    with pytest.raises(SceneSpecError, match="not a plain name"):
        load_gt_edit(tiny_scene, "../../snow", "view_000.png")
    with pytest.raises(SceneSpecError, match="not a file name"):
        load_gt_edit(tiny_scene, "snow", "../../images/view_000.png")
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    outside = _outside_image(tiny_scene, tmp_path)
    target = scene / "gt" / "edits" / "snow" / "images" / "view_000.png"
    target.unlink()
    os.symlink(outside, target)
    with pytest.raises(SceneSpecError, match=r"ground-truth file 'gt/edits/snow/images/view_000\.png'.*outside"):
        load_gt_edit(scene, "snow", "view_000.png")
    with pytest.raises(InputError, match=r"ground-truth file 'gt/edits/snow/images/view_000\.png'.*outside"):
        preprocess(scene, tmp_path / "out", PreprocessConfig(method="nerfstudio"))


# ---- names in workflows and the folders a run writes ----------------------------------------------------

def _victim(tmp_path) -> Path:
    victim = tmp_path / "elsewhere" / "victim"
    (victim / "images").mkdir(parents=True)
    (victim / "scene.toml").write_text(
        '[scene]\nname = "victim"\n[[edits]]\nid = "snow"\ninstruction = "Make it snow"\n'
        'source_caption = "a"\ntarget_caption = "b"\n')
    (tmp_path / "scenes").mkdir()
    return victim


@pytest.mark.parametrize("override", ["scene=../elsewhere/victim", "scene=/etc", "scene=a b",
                                      "name=../../up", "edit=../../x"])
def test_workflow_names_substituted_into_folders_must_be_plain(tmp_path, override):
    from experiments.workflow import load_workflow

    _victim(tmp_path)
    with pytest.raises(PathError, match=r"ablation\.toml: \[workflow\] .* is not a plain name.*letters, digits"):
        load_workflow(ABLATION, [f"scenes_dir={tmp_path / 'scenes'}", override])


def test_run_command_refuses_a_traversing_scene_before_writing_anything(tmp_path, monkeypatch, capsys):
    from experiments.cli import main

    _victim(tmp_path)
    monkeypatch.chdir(tmp_path)
    status = main(["--cache", "cache", "--runs", "runs", "run", str(ABLATION), "--set", "scenes_dir=scenes",
                   "--set", "scene=../elsewhere/victim"])
    assert status == 2
    assert "is not a plain name" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["elsewhere", "scenes"]


def test_plain_name_and_confined_helpers(tmp_path):
    assert check_plain_name("campsite_2.v1", "scene") == "campsite_2.v1"
    for bad in ("", ".hidden", "a/b", "..", "x" * 101, "caf\u00e9", None):
        with pytest.raises(PathError, match="plain name"):
            check_plain_name(bad, "scene")
    assert confined(tmp_path / "runs" / "a", tmp_path / "runs", "run folder") == tmp_path / "runs" / "a"
    with pytest.raises(PathError, match=r"run folder .* outside"):
        confined(tmp_path / "runs" / ".." / "x", tmp_path / "runs", "run folder")
    (tmp_path / "runs").mkdir()
    os.symlink(tmp_path, tmp_path / "runs" / "link")
    with pytest.raises(PathError, match="outside"):
        confined(tmp_path / "runs" / "link" / "x", tmp_path / "runs", "run folder")


@pytest.mark.parametrize("field, value", [("name", "../escape.png"), ("file", "../outside.png")])
def test_a_dataset_naming_files_outside_itself_is_refused(tiny_dataset, tmp_path, field, value):
    from dualnerf.dataset import DatasetError, load_dataset

    folder = tmp_path / "ds"
    shutil.copytree(tiny_dataset, folder)
    doc = json.loads((folder / "cameras.json").read_text())
    shutil.copyfile(folder / doc["frames"][0]["file"], tmp_path / "outside.png")
    doc["frames"][0][field] = value
    (folder / "cameras.json").write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=rf"frame 0.*{field} '\.\./"):
        load_dataset(folder)


def test_report_folder_stays_inside_the_folder_its_template_names(tmp_path, monkeypatch):
    from experiments.workflow import load_workflow

    monkeypatch.chdir(tmp_path)
    wf = load_workflow(ABLATION, ["scenes_dir=/nonexistent", "report_dir=out/reports/{scene}"])
    assert wf.report_dir == Path("out/reports/campsite")
    (tmp_path / "out" / "reports").mkdir(parents=True)
    os.symlink(tmp_path, tmp_path / "out" / "reports" / "campsite")      # a link out of out/reports/
    with pytest.raises(PathError, match=r"\[workflow\] report_dir 'out/reports/campsite' resolves to .* outside"):
        load_workflow(ABLATION, ["scenes_dir=/nonexistent", "report_dir=out/reports/{scene}"])
