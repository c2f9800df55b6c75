"""fitting.keypoints: the keypoint formats' facts agree with each other and with the formats."""
import numpy as np

from softras_cl.fitting.keypoints import face_mesh, ibug68, pose33

IBUG68_PARTS = (ibug68.JAW, ibug68.RIGHT_BROW, ibug68.LEFT_BROW, ibug68.NOSE_BRIDGE, ibug68.NOSTRILS,
                ibug68.RIGHT_EYE, ibug68.LEFT_EYE, ibug68.OUTER_LIPS, ibug68.INNER_LIPS)


def test_ibug68_parts_cover_every_point_once_in_order():
    assert [i for part in IBUG68_PARTS for i in part] == list(range(ibug68.COUNT))
    assert ibug68.COUNT == 68 and len(ibug68.NAMES) == 68 and len(ibug68.JAW) == 17
    assert list(ibug68.BROWS) == [*ibug68.RIGHT_BROW, *ibug68.LEFT_BROW]
    assert list(ibug68.MOUTH) == [*ibug68.OUTER_LIPS, *ibug68.INNER_LIPS]


def test_ibug68_named_points_are_what_their_names_say():
    names = ibug68.NAMES
    assert names[ibug68.CHIN] == "chin" and names[ibug68.NOSE_TIP] == "nose tip"
    assert names[ibug68.NOSE_BRIDGE_TOP] == "nose bridge top"
    assert [names[i] for i in ibug68.OUTER_EYE_CORNERS] == ["right eye outer corner", "left eye outer corner"]
    assert all(names[i].startswith("jaw") or names[i] == "chin" for i in ibug68.JAW)
    assert all("eye" in names[i] for part in (ibug68.RIGHT_EYE, ibug68.LEFT_EYE) for i in part)
    assert all("inner" in names[i] for i in ibug68.INNER_LIPS)


def test_ibug68_outlines():
    assert ibug68.FACE_OUTLINE == tuple(range(0, 17)) + tuple(range(26, 16, -1))
    assert [list(r) for r in ibug68.OPENINGS] == [list(range(36, 42)), list(range(42, 48)), list(range(60, 68))]


def test_face_mesh_ties():
    m = face_mesh.MP468_TO_IBUG68
    assert m.shape == (ibug68.COUNT,) and m.dtype == np.int64
    assert len(set(m.tolist())) == ibug68.COUNT
    assert (m >= 0).all() and (m < face_mesh.COUNT).all()
    assert face_mesh.WITH_IRISES == 478
    # well-known Face Mesh vertices: eye corners, mouth corners, chin, nose tip
    assert (m[36], m[39], m[42], m[45]) == (33, 133, 362, 263)
    assert (m[48], m[54], m[8], m[30]) == (61, 291, 152, 4)


def test_pose33_names_and_torso():
    assert pose33.COUNT == len(pose33.NAMES) == len(set(pose33.NAMES)) == 33
    assert pose33.TORSO == (11, 12, 23, 24)
    for keypoint, _, _ in pose33.KEYPOINT_MAP:
        assert all(0 <= k < pose33.COUNT for k in np.atleast_1d(keypoint))
    same_name = [(k, name) for k, name, _ in pose33.KEYPOINT_MAP if np.ndim(k) == 0 and name in pose33.NAMES]
    assert all(pose33.NAMES[k] == name for k, name in same_name) and len(same_name) >= 12
