import numpy as np
import pytest

from softras_cl.io.landmarks import read_landmarks, write_pts


def points68(seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(10, 200, size=(68, 2))


def pts_text(points, n=None):
    body = "\n".join(f"{x:.6f} {y:.6f}" for x, y in points)
    return f"version: 1\nn_points:  {len(points) if n is None else n}\n{{\n{body}\n}}\n"


def test_pts_is_one_based(tmp_path):
    p = points68()
    path = tmp_path / "face.pts"
    path.write_text(pts_text(p))
    np.testing.assert_allclose(read_landmarks(path), p - 1.0, atol=1e-6)


@pytest.mark.parametrize("sep", [" ", "\t", ",", ", "])
def test_text_rows_are_zero_based(tmp_path, sep):
    p = points68()
    path = tmp_path / "face.txt"
    path.write_text("# x y\n" + "\n".join(f"{x!r}{sep}{y!r}" for x, y in p.tolist()) + "\n")
    np.testing.assert_array_equal(read_landmarks(path), p)


def test_npy(tmp_path):
    p = points68()
    path = tmp_path / "face.npy"
    np.save(path, p.astype(np.float32))
    out = read_landmarks(path)
    assert out.dtype == np.float64 and out.shape == (68, 2)
    np.testing.assert_array_equal(out, p.astype(np.float32))


def test_format_comes_from_content(tmp_path):
    p = points68()
    path = tmp_path / "face.txt"
    path.write_text(pts_text(p))
    np.testing.assert_allclose(read_landmarks(path), p - 1.0, atol=1e-6)


def test_write_pts_round_trip(tmp_path):
    p = points68()
    path = tmp_path / "out.pts"
    write_pts(path, p)
    text = path.read_text()
    assert text.startswith("version: 1\nn_points: 68\n{\n") and text.rstrip().endswith("}")
    np.testing.assert_allclose(read_landmarks(path), p, rtol=0, atol=1e-12)
    first = [float(t) for t in text.splitlines()[3].split()]
    np.testing.assert_allclose(first, p[0] + 1.0)


def test_wrong_count(tmp_path):
    path = tmp_path / "short.txt"
    np.savetxt(path, points68()[:67])
    with pytest.raises(ValueError, match="landmark file .*short.txt has 67 points, the model expects 68"):
        read_landmarks(path)
    assert read_landmarks(path, n_points=None).shape == (67, 2)


def test_pts_header_disagrees_with_block(tmp_path):
    path = tmp_path / "bad.pts"
    path.write_text(pts_text(points68(), n=70))
    with pytest.raises(ValueError, match="header says n_points 70 but the block holds 68 points"):
        read_landmarks(path)


def test_nan_point_is_named(tmp_path):
    p = points68()
    p[12] = [np.nan, 3.0]
    path = tmp_path / "nan.npy"
    np.save(path, p)
    with pytest.raises(ValueError, match=r"nan.npy: point 12 is \(x=nan, y=3.0\), not finite"):
        read_landmarks(path)


def test_points_outside_the_image(tmp_path):
    p = points68()
    p[5] = [639.6, 100.0]
    path = tmp_path / "face.npy"
    np.save(path, p)
    with pytest.raises(ValueError, match=r"point 5 at \(x=639.6, y=100\) is outside the 640x480 \(W x H\) image"):
        read_landmarks(path, image_size=(480, 640))
    p[5] = [639.5, -0.5]  # the outer edges of the corner pixels are on the image
    np.save(path, p)
    assert read_landmarks(path, image_size=(480, 640)).shape == (68, 2)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.pts"):
        read_landmarks(tmp_path / "nope.pts")


@pytest.mark.parametrize("content, message", [
    (b"\xff\xfe\x00garbage", "neither .npy nor text"),
    (b"1 2\n3 four\n", "line 2 is not 'x y'"),
    (b"1 2 3\n", "line 1 is not 'x y'"),
    (b"version: 1\nn_points: 2\n1 2\n3 4\n", "not a .pts file"),
    (b"version: 1\nn_points: 1\n{\n1 x\n}\n", "non-numeric entry"),
    (b"\x93NUMPY\x01\x00", "unreadable .npy"),
])
def test_unreadable_files(tmp_path, content, message):
    path = tmp_path / "bad.dat"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=f"bad.dat.*{message}"):
        read_landmarks(path, n_points=None)


def test_npy_of_wrong_shape(tmp_path):
    path = tmp_path / "three.npy"
    np.save(path, np.zeros((68, 3)))
    with pytest.raises(ValueError, match=r"expected an \(N, 2\) numeric array"):
        read_landmarks(path)


def test_write_pts_rejects_bad_points(tmp_path):
    with pytest.raises(ValueError, match=r"shape \(N, 2\)"):
        write_pts(tmp_path / "x.pts", np.zeros((3, 3)))
    with pytest.raises(ValueError, match="NaN"):
        write_pts(tmp_path / "x.pts", np.array([[np.nan, 1.0]]))
