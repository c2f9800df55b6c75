"""Mitsuba 3's path-traced synthetic faces (softras_cl.validate.mitsuba_face, bench face
--renderers mitsuba): the environment map is the SH light, the sun lights what it should, and a
face's photo agrees with softras-cl's in geometry but not in shading. Runs only when the optional
extra is installed (pip install 'softras-cl[validate]')."""
import numpy as np
import pytest
import trimesh

pytestmark = pytest.mark.mitsuba
pytest.importorskip("mitsuba", reason="Mitsuba 3 is an optional extra: pip install 'softras-cl[validate]'")

from softras_cl.errors import InputError
from softras_cl.scene.camera import Camera
from softras_cl.scene.shading import SHLight, sh_ambient
from softras_cl.validate.mitsuba_face import render_face_mitsuba, silhouette_iou, sun_and_sky

SIZE, FOCAL, ALBEDO = 48, 30.0, np.array([0.8, 0.6, 0.5])


def sphere_scene():
    m = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    centre = np.array([0.0, 0.0, -5.0])
    K = [[FOCAL, 0, SIZE / 2 - 0.5], [0, FOCAL, SIZE / 2 - 0.5], [0, 0, 1]]
    camera = Camera.from_opencv(K, np.diag([1.0, -1.0, -1.0]), np.zeros(3), (SIZE, SIZE))
    return np.asarray(m.vertices) + centre, np.asarray(m.faces), centre, camera


def sphere_normals(centre):
    """Unit normals (H, W, 3) of the exact sphere at each pixel centre's hit, the pixels well
    inside its silhouette and the silhouette (numpy float64 ray-sphere intersection)."""
    v, u = np.mgrid[0:SIZE, 0:SIZE]
    rays = np.stack([(u - (SIZE / 2 - 0.5)) / FOCAL, -(v - (SIZE / 2 - 0.5)) / FOCAL, -np.ones((SIZE, SIZE))], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    b = rays @ centre
    disc = b * b - (centre @ centre - 1.0)
    inside = disc > 0.3 * disc.max()
    t = b - np.sqrt(np.clip(disc, 0, None))
    return rays * t[..., None] - centre, inside, disc > 0


def positive_sh():
    """An SH light whose radiance is positive everywhere (so the environment map is not clipped)."""
    sh = sh_ambient([0.7, 0.63, 0.56])
    sh[:, 1:4] += np.array([0.1, 0.05, -0.08]) * sh[0, 0]
    sh[:, 4:] += 0.03 * sh[0, 0] * np.array([1.0, -1.0, 0.5, 1.0, -0.5])
    return sh


def expected_sphere(sh, normals, sun_share):
    """softras-cl's SH shading of the sphere scaled by 1 - sun_share, plus the sun's Lambert term."""
    sky, direction, irradiance = sun_and_sky(sh, sun_share)
    assert sky.min() > 0
    albedo = np.broadcast_to(ALBEDO, normals.shape)
    shade = SHLight(sh).shade(normals[None], albedo[None])[0][0]
    return (1 - sun_share) * shade + albedo * irradiance / np.pi * np.clip(normals @ direction, 0, None)[:, None]


@pytest.mark.parametrize("sun_share", [0.0, 0.4])
def test_sphere_in_the_sh_environment_shows_softras_shading(sun_share):
    """A convex sphere has no shadows and no bounces: Mitsuba's path tracer must reproduce the SH
    irradiance (the envmap's direction mapping) plus the sun's Lambert term, up to Monte Carlo
    noise (~1% per pixel at 256 rays). A mirrored light axis gives 5-10% median error."""
    world, faces, centre, camera = sphere_scene()
    sh = positive_sh()
    out = render_face_mitsuba(world, faces, np.tile(ALBEDO, (len(world), 1)), camera, sh, spp=256,
                              sun_share=sun_share)
    normals, inside, silhouette = sphere_normals(centre)
    expected = expected_sphere(sh, normals[inside], sun_share)
    rel = np.abs(out["rgb"][inside] - expected) / expected
    assert np.median(rel) < 0.025
    assert np.abs(out["rgb"][inside].mean(0) / expected.mean(0) - 1).max() < 0.01
    assert (out["alpha"][inside] == 1).all() and silhouette_iou(out["alpha"], silhouette) > 0.95


def test_sun_is_mirrored_to_the_camera_side():
    sh = positive_sh()
    sh[:, 2] = -0.5 * sh[0, 0]                         # first order along -z: behind a face seen from +z
    _, behind, _ = sun_and_sky(sh)
    _, front, irradiance = sun_and_sky(sh, front=[0.0, 0.0, 1.0])
    assert behind[2] < 0 and front[2] == pytest.approx(-behind[2]) and front[:2] == pytest.approx(behind[:2])
    assert irradiance == pytest.approx(np.pi * 0.4 * np.array([0.7, 0.63, 0.56]))


def test_bad_inputs_are_named():
    world, faces, _, camera = sphere_scene()
    with pytest.raises(InputError, match="spp"):
        render_face_mitsuba(world, faces, np.ones_like(world), camera, positive_sh(), spp=1)
    with pytest.raises(InputError, match="sh must be"):
        sun_and_sky(np.zeros((3, 4)))
    with pytest.raises(InputError, match="sun_share"):
        sun_and_sky(positive_sh(), 1.0)


def test_face_photo_differs_in_shading_not_in_geometry(demo_face_model):
    """bench face's Mitsuba photo of a synthetic face: the same silhouette as softras-cl's photo
    of the same truth, the same background, but other shading (shadows, sun, bounces)."""
    from softras_cl.bench.face import mitsuba_noise, mitsuba_sample, synthetic_face

    sample = synthetic_face(demo_face_model, np.random.default_rng(2), 64)
    m = mitsuba_sample(demo_face_model, sample, spp=16)
    check = m["render_check"]
    assert check["silhouette_iou"] > 0.95
    assert 0.02 < check["rms_vs_softras"] < 0.3
    background = (m["alpha"] == 0) & (sample["alpha"] == 0)
    assert np.allclose(m["photo"][background], sample["photo"][background])
    assert m["landmarks"] is sample["landmarks"]
    noise = mitsuba_noise(demo_face_model, sample, spp=16)
    assert 0.002 < noise < check["rms_vs_softras"]


def test_bench_face_on_mitsuba_photos(tmp_path, capsys):
    """A bench of one face in each of two yaw bins on Mitsuba's photos: its rows, the render
    checks of every bin's photo and its strip."""
    import json

    from softras_cl.cli import main

    out = tmp_path / "bench"
    assert main(["bench", "face", "--faces", "1", "--size", "64", "--budgets", "fast", "--renderers", "mitsuba",
                 "--yaws", "0-15,15-45", "--spp", "4", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "mitsuba photos (4 spp)" in text and "Monte Carlo noise" in text
    doc = json.loads((out / "face.json").read_text())
    assert list(doc["summary"]) == [f"mitsuba/yaw {b}/{budget}" for b in ("0-15", "15-45")
                                    for budget in ("landmarks-only", "fast")]
    assert {s["renderer"] for s in doc["summary"].values()} == {"mitsuba"}
    assert len(doc["mitsuba"]["faces"]) == 2                     # both bins' photos, not the last bin's
    assert all(c["silhouette_iou"] > 0.95 for c in doc["mitsuba"]["faces"]) and doc["mitsuba"]["noise_rms"][0] > 0
    assert (out / "face_mitsuba_strip.png").stat().st_size > 0 and not (out / "face_strip.png").exists()
