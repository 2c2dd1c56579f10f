"""The examples run as their READMEs say (on small images here)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

import diffshade as ds
from diffshade import color as _color

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def test_the_photographs_data_set_is_what_its_readme_says(tmp_path, monkeypatch):
    spec = importlib.util.spec_from_file_location("make_dataset", EXAMPLES / "photographs" / "make_dataset.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    monkeypatch.setattr(mod, "SIZE", 32)
    mod.main(tmp_path)
    truth = json.loads((tmp_path / "truth.json").read_text())
    mesh = ds.load_mesh(tmp_path / "object.ply")
    assert mesh.colors is not None and len(truth["albedo"]) == mesh.vertices.shape[0]
    for i in range(len(mod.VIEWS)):
        enc, _ = _color.png_encoding(tmp_path / f"view{i}.png")
        assert enc == "srgb"
        cam = ds.load_camera(tmp_path / f"view{i}.json")
        assert isinstance(cam, ds.OpenCVCamera) and cam.resolution == (32, 32)
    for setup in ("a", "b"):
        scene, opts = ds.load_scene(tmp_path / f"setup_{setup}.toml")
        assert opts.raster.vertex_color == "diffuse" and scene.point.count == 1
    np.testing.assert_allclose(truth["white_balance"]["view[1]"], 1.25 * np.array([1.08, 1.0, 0.86]))
