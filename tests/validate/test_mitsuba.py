"""softras-cl against Mitsuba 3: silhouette, depth and flat Lambert shading
agree at sharp settings. Runs only when the optional extra is installed (pip install
'softras-cl[validate]'); see softras_cl/validate/mitsuba.py for how the two renderers are made to
compute the same thing."""
import json
import math
import sys

import numpy as np
import pytest
import trimesh

pytestmark = pytest.mark.mitsuba
pytest.importorskip("mitsuba")

from softras_cl.scene.camera import Camera
from softras_cl.cli import main
from softras_cl.errors import EXIT_INPUT
from softras_cl.validate.compare import default_camera, interior
from softras_cl.io.meshes import Mesh, save_mesh
from softras_cl.validate.mitsuba import compare_mitsuba, mitsuba_available, render_mitsuba
from softras_cl.validate.raycast import raycast
from softras_cl.scene.renderer import SHADINGS

from support import comparison_meshes

SIZE = 128


def _colored(vertices, faces):
    """Smoothly varying vertex colours, so per-face albedo (mean of the corners) is tested too."""
    return Mesh(vertices, faces, colors=0.5 + 0.4 * np.tanh(2.0 * vertices))


def icosphere():
    plain = comparison_meshes.icosphere()
    return _colored(plain.vertices, plain.faces)


def torus():
    plain = comparison_meshes.torus()
    return _colored(plain.vertices, plain.faces)


MESHES = {"icosphere": icosphere, "torus": torus}


def test_available():
    assert mitsuba_available()


@pytest.mark.parametrize("name", sorted(MESHES))
def test_sharp_limit_matches_mitsuba(name):
    """sigma 1e-7, gamma 1e-6, dist_eps 0.49; flat Lambert (face normals, face albedo) under a
    headlight, no ambient, Mitsuba's black background."""
    result = compare_mitsuba(MESHES[name](), default_camera(SIZE, elevation_deg=40), dist_eps=0.49)
    m = result.metrics
    assert m["silhouette_iou"] >= 0.995
    assert m["interior_pixels"] > 4000
    assert m["depth_rel_err_max"] < 1e-3
    assert m["psnr_db"] >= 40.0
    assert m["shadowed_pixels"] < 10                  # the headlight leaves almost no shadows
    lit = result.ref_rgb[result.ref.mask]
    assert lit.mean() > 0.2 and lit.std() > 0.05      # a shaded, coloured image, not a blank one


@pytest.mark.parametrize("size", [(48, 64), (70, 40)])
def test_camera_conventions_and_pixel_centres(size):
    """Non-square images and an off-centre principal point: Mitsuba's hits are the ray cast's
    (same pixels, same faces, same camera-frame depth), so its rays pass through our pixel
    centres with our image orientation."""
    m = trimesh.creation.icosphere(2)
    v, f = np.asarray(m.vertices, float), np.asarray(m.faces)
    cam = Camera.look_at([1.0, 2.0, 4.5], [0.1, 0.05, 0.0], fov_deg=35, image_size=size)
    cam = cam.with_params(cx=cam.cx + 7.3, cy=cam.cy - 4.6)
    out, ref = render_mitsuba(v, f, cam), raycast(v, f, cam)
    assert out["mask"].sum() > 300
    assert np.array_equal(out["mask"], ref.mask)
    assert (out["face"][ref.mask] == ref.face[ref.mask]).mean() > 0.995
    np.testing.assert_allclose(out["depth"][ref.mask], ref.depth[ref.mask], rtol=1e-5)
    assert np.isnan(out["depth"][~ref.mask]).all() and (out["face"][~ref.mask] == -1).all()


def test_lambert_is_exact():
    """directional irradiance pi * I on a diffuse surface gives albedo * I * max(0, n . l)."""
    v = np.array([[-10.0, -10.0, 0.0], [10.0, -10.0, 0.0], [0.0, 10.0, 0.0]])   # normal +z
    f = np.array([[0, 1, 2]])
    cam = Camera.look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], fov_deg=40, image_size=(16, 20))
    albedo = np.tile([0.2, 0.5, 0.9], (3, 1))
    light, intensity = (math.sin(1.0), 0.0, math.cos(1.0)), np.array([1.0, 0.5, 2.0])
    out = render_mitsuba(v, f, cam, albedo, light, intensity)
    assert out["mask"].all()
    np.testing.assert_allclose(out["rgb"], np.broadcast_to(albedo[0] * intensity * math.cos(1.0), (16, 20, 3)),
                               rtol=1e-5)
    np.testing.assert_allclose(out["depth"], 3.0, rtol=1e-6)
    assert (render_mitsuba(v, f, cam, albedo, (0.0, 0.3, -1.0), intensity)["rgb"] == 0).all()
    grey = render_mitsuba(v, f, cam, None, (0.0, 0.0, 1.0), 1.0)["rgb"]    # no albedo: grey 0.7
    np.testing.assert_allclose(grey, 0.7, rtol=1e-5)


def test_shadows_are_counted():
    """Mitsuba casts shadows, the rasteriser none: a light from above the camera shadows the
    torus's hole; a convex mesh is never shadowed."""
    cam = default_camera(SIZE, elevation_deg=40)
    R = cam.rotation_matrix()
    light = math.cos(math.radians(30)) * -R[2] + math.sin(math.radians(30)) * -R[1]
    assert compare_mitsuba(torus(), cam, light_direction=light).metrics["shadowed_pixels"] > 100
    assert compare_mitsuba(icosphere(), cam, light_direction=light).metrics["shadowed_pixels"] == 0


@pytest.mark.skipif("pixel" not in SHADINGS, reason="the renderer has no per-pixel shading")
def test_per_pixel_shading_matches_smooth_normals():
    """Renderer(shading="pixel") against Mitsuba shading with interpolated vertex normals and
    vertex colours."""
    result = compare_mitsuba(icosphere(), default_camera(SIZE, elevation_deg=40), shading="pixel")
    m = result.metrics
    assert m["silhouette_iou"] >= 0.995 and m["depth_rel_err_max"] < 1e-3
    assert m["psnr_db"] >= 40.0
    inner = interior((result.ours_alpha > 0.5) & result.ref.mask)
    assert np.abs(result.ours_rgb - result.ref_rgb)[inner].max() < 1e-3


def test_textured_unlit():
    """Unlit texture: Mitsuba's area emitter with a bilinear bitmap radiance at the hit's uv."""
    m = compare_mitsuba(comparison_meshes.textured_sphere(), default_camera(256, elevation_deg=40)).metrics
    assert m["silhouette_iou"] >= 0.995
    assert m["depth_rel_err_max"] < 1e-3
    assert m["psnr_db"] >= 40.0


def test_bad_input():
    v = np.asarray(trimesh.creation.icosphere(1).vertices, float)
    f = np.asarray(trimesh.creation.icosphere(1).faces)
    cam = default_camera(16)
    with pytest.raises(ValueError, match="perspective"):
        render_mitsuba(v, f, Camera.orthographic([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], image_size=(16, 16)))
    with pytest.raises(ValueError, match="square pixels"):
        render_mitsuba(v, f, cam.with_params(fy=cam.fy * 1.1))
    with pytest.raises(ValueError, match="albedo"):
        render_mitsuba(v, f, cam, albedo=np.ones((3, 3)))
    with pytest.raises(ValueError, match="no faces"):
        render_mitsuba(v, np.zeros((0, 3), int), cam)
    with pytest.raises(ValueError, match="light_direction"):
        render_mitsuba(v, f, cam, light_direction=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="shading"):
        render_mitsuba(v, f, cam, shading="vertex")


def test_missing_mitsuba_is_reported(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "mitsuba", None)          # import mitsuba -> ImportError
    assert not mitsuba_available()
    path = tmp_path / "ico.ply"
    mesh = icosphere()
    save_mesh(path, mesh.vertices, mesh.faces)
    assert main(["compare", str(path), "--reference", "mitsuba", "--size", "32",
                 "--out", str(tmp_path / "c.png")]) == EXIT_INPUT
    assert "pip install" in capsys.readouterr().err


def test_compare_command(tmp_path, capsys):
    path = tmp_path / "torus.ply"
    mesh = torus()
    save_mesh(path, mesh.vertices, mesh.faces, colors=mesh.colors)
    out = tmp_path / "c.png"
    assert main(["compare", str(path), "--reference", "mitsuba", "--size", "96", "--out", str(out), "--json"]) == 0
    m = json.loads(capsys.readouterr().out)
    assert m["reference"] == "mitsuba"
    assert m["silhouette_iou"] >= 0.995 and m["psnr_db"] >= 40.0 and "shadowed_pixels" in m
    assert out.stat().st_size > 0
    assert main(["compare", str(path), "--reference", "mitsuba", "--size", "64", "--out", str(out)]) == 0
    assert "Mitsuba's shadows" in capsys.readouterr().out
