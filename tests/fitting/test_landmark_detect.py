"""Example photos' shipped 68-point .pts files, the MediaPipe 468->68 table, and the optional
`landmarks` extra's error when mediapipe is missing (no mediapipe is needed to run these)."""
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from softras_cl import cli
from softras_cl.fitting import landmark_detect as ld

DATA = Path(__file__).resolve().parents[2] / "examples" / "data"
PHOTOS = {"astronaut": "astronaut.png", "grace_hopper": "grace_hopper.jpg"}


def _read_pts(path: Path) -> np.ndarray:
    """Own minimal iBUG .pts reader: returns 0-based pixel coordinates (file is 1-based)."""
    lines = [l.strip() for l in path.read_text().splitlines() if l.strip()]
    assert lines[0] == "version: 1"
    assert lines[1].replace(" ", "") == "n_points:68"
    assert lines[2] == "{" and lines[-1] == "}"
    pts = np.array([[float(v) for v in l.split()] for l in lines[3:-1]])
    assert pts.shape == (68, 2)
    return pts - 1.0


@pytest.fixture(scope="module", params=sorted(PHOTOS))
def face(request):
    name = request.param
    with Image.open(DATA / PHOTOS[name]) as im:
        size = im.size  # (W, H)
    return name, _read_pts(DATA / f"{name}.pts"), size


def test_points_inside_photo(face):
    _, p, (w, h) = face
    assert np.isfinite(p).all()
    assert (p[:, 0] >= 0).all() and (p[:, 0] <= w - 1).all()
    assert (p[:, 1] >= 0).all() and (p[:, 1] <= h - 1).all()
    assert len({tuple(q) for q in p}) >= 60  # not collapsed (inner-lip points may meet)


def test_order_and_handedness(face):
    """Checks that fail on a mirrored or permuted point order (frontal, upright faces)."""
    _, p, _ = face
    x, y = p[:, 0], p[:, 1]
    r_eye, l_eye = p[36:42], p[42:48]
    iod = np.linalg.norm(r_eye.mean(0) - l_eye.mean(0))
    assert iod > 20
    # subject's right eye (36-41) is on the left of the image
    assert r_eye[:, 0].max() < l_eye[:, 0].min()
    # eye corners: 36 outer (leftmost of its eye), 39 inner; 42 inner, 45 outer (rightmost)
    assert x[36] == r_eye[:, 0].min() and x[39] == r_eye[:, 0].max()
    assert x[42] == l_eye[:, 0].min() and x[45] == l_eye[:, 0].max()
    # upper lids (37, 38, 43, 44) above lower lids (41, 40, 47, 46)
    assert y[37] < y[41] and y[38] < y[40] and y[43] < y[47] and y[44] < y[46]
    # brows left to right, each above its eye
    assert np.all(np.diff(x[17:22]) > 0) and np.all(np.diff(x[22:27]) > 0)
    assert x[17:22].mean() < x[22:27].mean()
    assert y[17:22].mean() < r_eye[:, 1].min() and y[22:27].mean() < l_eye[:, 1].min()
    # nose: bridge runs down to the tip (30), tip between the eyes in x and below them
    assert np.all(np.diff(y[27:31]) > 0)
    assert x[39] < x[30] < x[42] and y[30] > max(r_eye[:, 1].max(), l_eye[:, 1].max())
    assert np.all(np.diff(x[31:36]) > 0) and y[33] > y[30] - 0.02 * iod
    # mouth below the nose; corners 48 (left of image) and 54; 51 top, 57 bottom of the lips
    mouth = p[48:68]
    assert mouth[:, 1].min() > y[33] - 0.05 * iod
    assert x[48] < x[51] < x[54] and x[48] == mouth[:12, 0].min() and x[54] == mouth[:12, 0].max()
    assert y[51] < y[62] <= y[66] + 1e-9 < y[57] + 1e-9
    assert np.all(np.diff(x[48:55]) > 0) and np.all(np.diff(x[54:60]) < 0)
    # jaw 0..16 runs left to right, 8 (chin) is the lowest point of all 68
    # (the upper jaw points are nearly vertical, so a small backward step is allowed)
    assert np.all(np.diff(x[0:17]) > -0.05 * iod) and x[0] < x[4] < x[8] < x[12] < x[16]
    assert x[0:8].max() < x[8] < x[9:17].min()
    assert y[8] == y.max()
    assert np.all(np.diff(y[0:9]) > 0) and np.all(np.diff(y[8:17]) < 0)


def test_shipped_pts_match_writer_format(face):
    """The committed files are what format_pts writes (1-based, 3 decimals)."""
    name, p, _ = face
    assert (DATA / f"{name}.pts").read_text() == ld.format_pts(p)


def test_shipped_pts_read_by_fitting_reader(face):
    """fit-face's reader gives the same 0-based points, all on the image."""
    from softras_cl.io.landmarks import read_landmarks

    name, p, (w, h) = face
    np.testing.assert_allclose(read_landmarks(DATA / f"{name}.pts", image_size=(h, w)), p, atol=1e-9)


def test_mapping_table():
    m = ld.MP468_TO_IBUG68
    assert m.shape == (68,) and np.issubdtype(m.dtype, np.integer)
    assert len(set(m.tolist())) == 68
    assert (m >= 0).all() and (m < 468).all()
    assert len(ld.IBUG68_NAMES) == 68
    # well-known Face Mesh vertices: eye corners, mouth corners, chin, nose tip
    assert (m[36], m[39], m[42], m[45]) == (33, 133, 362, 263)
    assert (m[48], m[54], m[8], m[30]) == (61, 291, 152, 4)


def test_format_pts_is_one_based():
    text = ld.format_pts(np.array([[0.0, 0.0], [9.5, 19.25]]))
    assert text == "version: 1\nn_points: 2\n{\n1.000 1.000\n10.500 20.250\n}\n"
    with pytest.raises(ValueError):
        ld.format_pts(np.zeros((3, 3)))


@pytest.fixture
def no_mediapipe(monkeypatch):
    """Make `import mediapipe` fail even where it is installed."""
    import sys

    for mod in [k for k in sys.modules if k == "mediapipe" or k.startswith("mediapipe.")]:
        monkeypatch.delitem(sys.modules, mod)
    monkeypatch.setitem(sys.modules, "mediapipe", None)


def test_detect_without_mediapipe_says_how_to_install(no_mediapipe):
    img = np.zeros((32, 32, 3), np.uint8)
    with pytest.raises(ImportError, match=r'pip install "softras-cl\[landmarks\]"') as e:
        ld.detect_landmarks(img)
    assert "numpy<2" in str(e.value)


def test_detect_rejects_bad_image():
    with pytest.raises(ValueError, match="uint8"):
        ld.detect_landmarks(np.zeros((8, 8), np.float32))


def test_cli_without_mediapipe(no_mediapipe, tmp_path, capsys):
    out = tmp_path / "x.pts"
    code = cli.main(["detect-landmarks", str(DATA / "astronaut.png"), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and not out.exists()
    assert 'pip install "softras-cl[landmarks]"' in err and "numpy<2" in err


def test_cli_help_lists_detect_landmarks(capsys):
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    assert "detect-landmarks" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli.main(["detect-landmarks", "--help"])
    out = capsys.readouterr().out
    assert "--out" in out and "--overlay" in out and "PHOTO" in out


def test_draw_landmarks_overlay():
    img = np.zeros((40, 50, 3), np.uint8)
    pts = np.stack([np.linspace(5, 45, 68), np.linspace(5, 35, 68)], 1)
    out = ld.draw_landmarks(img, pts, scale=2.0)
    assert out.size == (100, 80)
    assert np.asarray(out).any()
