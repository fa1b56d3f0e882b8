"""File paths in scene files: relative to the scene file's folder, written back absolute (portable scenes)."""

import os

import pytest

from scenes.scene import load_scene

SCENE = """
[telescope]
pixel_scale_arcsec = 1.0
[detector]
preset = "ml11002"
width = 64
height = 64
[pointing]
ra_deg = 120.0
dec_deg = -30.0
[sky]
stars = true
catalog = "stars.csv"
[effects.vignetting]
a2 = 0.01
"""


@pytest.fixture
def relative_scene(tmp_path, monkeypatch):
    """A scene at the *relative* path out/x/s.toml (cwd = tmp_path) naming its catalogue relatively."""
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "out" / "x"
    folder.mkdir(parents=True)
    (folder / "stars.csv").write_text("ra,dec,mag\n120.0,-30.0,11.0\n")
    (folder / "s.toml").write_text(SCENE)
    return os.path.join("out", "x", "s.toml")


def test_relative_catalogue_of_a_relative_scene_becomes_absolute(relative_scene, tmp_path):
    sc = load_scene(relative_scene)
    assert sc.sky.catalog == str(tmp_path / "out" / "x" / "stars.csv")
    assert os.path.isabs(sc.resolved()["sky"]["catalog"])


def test_scene_written_by_diagnose_apply_reloads_from_anywhere(relative_scene, tmp_path, monkeypatch):
    """The bug of docs/compare_realdata_sky.md sect. 4 item 4: round 2 looked for out/x/out/x/stars.csv."""
    from scenes.app.compare.apply import apply_candidate

    cand = {"effect": "column_defects", "params": {"count": 3}, "explanation": "test"}
    sc = load_scene(relative_scene)
    nxt = os.path.join("out", "x", "s_round2.toml")
    apply_candidate(sc, cand, nxt)
    sc2 = load_scene(nxt)  # the next round, same cwd, relative path
    assert sc2.sky.catalog == str(tmp_path / "out" / "x" / "stars.csv")
    (tmp_path / "elsewhere").mkdir()
    apply_candidate(sc2, cand, os.path.join("elsewhere", "s_round3.toml"))  # a scene away from its catalogue
    other = tmp_path / "other_cwd"
    other.mkdir()
    monkeypatch.chdir(other)  # another cwd, and a scene in another folder than its catalogue
    for p in (tmp_path / "out" / "x" / "s_round2.toml", tmp_path / "elsewhere" / "s_round3.toml"):
        sc3 = load_scene(str(p))
        assert sc3.sky.catalog == str(tmp_path / "out" / "x" / "stars.csv")
        assert "column_defects" in sc3.effects


def test_tle_file_and_effect_paths_are_written_back_absolute(tmp_path, monkeypatch):
    import shutil
    from pathlib import Path

    from scenes.scene import Scene, check_scene

    monkeypatch.chdir(tmp_path)
    (tmp_path / "sc").mkdir()
    shutil.copy(Path(__file__).parent / "data" / "iss_20191209.tle", tmp_path / "sc" / "iss.tle")
    data = {"objects": [{"tle_file": "iss.tle", "photons": 1.0}], "observer": {"tle_file": "iss.tle"},
            "effects": {"vignetting": {"map_file": "m.fits"}, "x": {"path": "../b.fits", "grid_file": "optics"}},
            "source": str(Path("sc") / "s.toml")}  # a relative scene path
    sc = Scene.model_validate(data)
    check_scene(sc)
    assert sc.objects[0]["tle_file"] == str(tmp_path / "sc" / "iss.tle")
    assert sc.observer["tle_file"] == str(tmp_path / "sc" / "iss.tle")
    assert sc.effects["vignetting"]["map_file"] == str(tmp_path / "sc" / "m.fits")
    assert sc.effects["x"]["path"] == str(tmp_path / "b.fits")  # '..' normalised
    assert sc.effects["x"]["grid_file"] == "optics"  # a keyword, not a file
    assert "tle_file" in sc.model_dump(exclude_unset=True)["objects"][0]
