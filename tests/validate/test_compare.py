"""softras-cl against an independent renderer (trimesh/Embree ray cast through every pixel
centre): silhouette, depth and shading agree at sharp settings."""
import numpy as np
import pytest
import trimesh

from softras_cl.cli import main
from softras_cl.validate.compare import compare_mesh, default_camera
from softras_cl.io.meshes import save_mesh

from support.comparison_meshes import icosphere, textured_sphere, torus


MESHES = {"icosphere": icosphere, "torus": torus, "textured": textured_sphere}


@pytest.mark.parametrize("name", sorted(MESHES))
def test_sharp_limit_matches_ray_cast(name):
    """sigma 1e-7, gamma 1e-6, dist_eps 0.49 (face footprints end 0.008 px past their edges)."""
    result = compare_mesh(MESHES[name](), default_camera(256, elevation_deg=40), dist_eps=0.49)
    m = result.metrics
    assert m["silhouette_iou"] >= 0.995
    assert m["interior_pixels"] > 15000
    assert m["depth_rel_err_max"] < 1e-3
    assert m["psnr_db"] >= 40.0


@pytest.mark.parametrize("name", sorted(MESHES))
def test_default_cutoff_against_ray_cast(name):
    """At the rendering default dist_eps 1e-4 each face's colour and depth reach 0.12 px past its
    edges (where, with gamma -> 0, the nearer face wins): the silhouette still agrees and depth
    agrees on all but a few pixels next to edges."""
    m = compare_mesh(MESHES[name](), default_camera(256, elevation_deg=40), dist_eps=1e-4).metrics
    assert m["silhouette_iou"] >= 0.995
    assert m["depth_rel_err_mean"] < 1e-4
    assert m["psnr_db"] >= 30.0


def test_compare_and_render_commands(tmp_path, capsys):
    path = tmp_path / "torus.ply"
    mesh = torus()
    save_mesh(path, mesh.vertices, mesh.faces, colors=0.5 + 0.4 * np.tanh(mesh.vertices))
    assert main(["compare", str(path), "--size", "96", "--out", str(tmp_path / "c.png"), "--json"]) == 0
    assert '"silhouette_iou"' in capsys.readouterr().out
    assert (tmp_path / "c.png").stat().st_size > 0
    assert main(["render", str(path), "--size", "64", "--out", str(tmp_path / "r.png"),
                 "--depth-out", str(tmp_path / "d.png"), "--light", "phong"]) == 0
    from softras_cl.io.images import read_image
    image = read_image(tmp_path / "r.png")
    assert image.shape == (64, 64, 3)
    assert (image.min(-1) < 0.95).mean() > 0.2 and image[0, 0].min() > 0.99   # shaded torus, white corner
    assert (tmp_path / "d.png").exists()


def test_render_command_reports_bad_mesh(tmp_path, run_cli):
    bad = tmp_path / "points.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(10, 3))).export(bad)
    result = run_cli("render", str(bad), "--out", str(tmp_path / "x.png"))
    assert result.code == 2                              # an input file problem (softras_cl.errors)
    assert "no faces" in result.err and "Traceback" not in result.err


def test_compare_without_embreex_names_the_extra(tmp_path, run_cli, monkeypatch):
    path = tmp_path / "torus.ply"
    mesh = torus()
    save_mesh(path, mesh.vertices, mesh.faces)
    monkeypatch.setattr(trimesh.ray, "has_embree", False)
    result = run_cli("compare", str(path), "--size", "32", "--out", str(tmp_path / "c.png"))
    assert result.code == 2 and "Traceback" not in result.err
    assert 'pip install "softras-cl[validate]"' in result.err
