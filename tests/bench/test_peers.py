"""Tests of `softras-cl bench peers` (softras_cl/bench/peers.py and the peer worker's pure parts).

They run without the peer environment: the harness is driven end to end with a STAND-IN peer
(tests/bench/standin_peer.py: softras-cl's float64 numpy reference, gradients by central
differences), so the protocol, the timing loop and the agreement check run for real, and the
stand-in broken on purpose must make the check fail. The real PyTorch3D worker is run only
where .venv-peers exists (scripts/setup_peers.sh).
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from softras_cl.bench import peer_pytorch3d as worker
from softras_cl.bench import peers
from softras_cl.bench.raster import make_scene, settings_for
from softras_cl.cli import main
from softras_cl.errors import EXIT_INPUT, EXIT_RESULT, InputError

STANDIN = Path(__file__).with_name("standin_peer.py")
TINY = ["--sizes", "16", "--faces", "80", "--repeats", "1"]


def run_standin(out: Path, *extra: str) -> tuple[int, dict]:
    """`bench peers` on the tiny scene against the stand-in: (exit code, peers.json or {})."""
    code = main(["bench", "peers", "--peer-python", sys.executable, "--peer-script", str(STANDIN),
                 *TINY, "--json", "--out", str(out), *extra])
    path = out / "peers.json"
    return code, json.loads(path.read_text()) if path.exists() else {}


# ---- the scene file ----------------------------------------------------------------------
def test_scene_round_trip(tmp_path):
    scene, settings = make_scene(80, 16, seed=3), settings_for(16, background=(0.1, 0.2, 0.3))
    peers.export_scene(tmp_path / "s.npz", scene, settings, faces_per_pixel=24)
    back, back_settings, k = peers.import_scene(tmp_path / "s.npz")
    for name in peers.SCENE_KEYS:
        np.testing.assert_array_equal(getattr(back, name), getattr(scene, name))
        assert getattr(back, name).dtype == getattr(scene, name).dtype
    assert (back.n_faces, back.size, k) == (80, 16, 24)
    assert back_settings == settings.replace(outputs=("rgb", "alpha"))
    raw = worker.load_scene(tmp_path / "s.npz")          # what the real worker reads
    assert tuple(raw["size"]) == (16, 16) and float(raw["sigma"]) == settings.sigma
    worker.check_scene(raw)


def test_worker_refuses_scenes_pytorch3d_cannot_match(tmp_path):
    scene, settings = make_scene(80, 16), settings_for(16)
    scene.vertices = scene.vertices * np.array([1.0, 1.0, 100.0])      # depths beyond far = 100
    peers.export_scene(tmp_path / "s.npz", scene, settings)
    with pytest.raises(ValueError, match="vertices: depths"):
        worker.check_scene(worker.load_scene(tmp_path / "s.npz"))
    peers.export_scene(tmp_path / "e.npz", make_scene(80, 16), settings_for(16, dist_eps=0.0))
    with pytest.raises(ValueError, match="dist_eps"):
        worker.check_scene(worker.load_scene(tmp_path / "e.npz"))


def test_blur_radius_is_the_cut_off():
    for sigma, eps in ((1e-5, 1e-4), (3e-4, 1e-2)):
        r = worker.blur_radius(sigma, eps)
        assert 1.0 / (1.0 + math.exp(r / sigma)) == pytest.approx(eps, rel=1e-12)


# ---- the comparison ----------------------------------------------------------------------
def agreeing_pair(rng):
    """(ours, peer) inputs of peers.compare that agree exactly."""
    rgb, alpha, grad = rng.random((4, 5, 3)), rng.random((4, 5)), rng.standard_normal((7, 3))
    ours = dict(rgb=rgb.astype(np.float32), alpha=alpha.astype(np.float32), grad=grad, grad_silhouette=2 * grad)
    peer = dict(rgb=rgb.astype(np.float32).astype(np.float64), alpha=alpha.astype(np.float32).astype(np.float64),
                grad_vertices=grad.copy(), grad_silhouette=2 * grad, clipping_differs=np.zeros((4, 5), bool))
    return ours, peer


def test_compare_metrics_on_known_differences():
    ours, peer = agreeing_pair(np.random.default_rng(0))
    m = peers.compare(ours, peer)
    assert m["agree"] and m["rgb_max"] == m["alpha_max"] == m["grad_rel"] == m["grad_silhouette_rel"] == 0.0

    peer["rgb"][1, 2, 0] += 0.25                  # where the clippings differ: reported, not checked
    peer["clipping_differs"][1, 2] = True
    m = peers.compare(ours, peer)
    assert m["agree"] and m["rgb_max"] == 0.0 and m["rgb_pixels_differ"] == 1
    assert m["rgb_max_all"] == pytest.approx(0.25)

    peer["rgb"][3, 4, 2] -= 2 * peers.RGB_TOL     # anywhere else: checked
    m = peers.compare(ours, peer)
    assert not m["agree"] and m["rgb_max"] == pytest.approx(2 * peers.RGB_TOL)

    ours, peer = agreeing_pair(np.random.default_rng(1))
    peer["alpha"][0, 0] += 2 * peers.ALPHA_TOL
    assert not peers.compare(ours, peer)["agree"]

    ours, peer = agreeing_pair(np.random.default_rng(2))
    peer["grad_vertices"] = 1.5 * peer["grad_vertices"]      # full gradient: reported only
    m = peers.compare(ours, peer)
    assert m["agree"] and m["grad_rel"] == pytest.approx(1 / 3)
    peer["grad_silhouette"] = peer["grad_silhouette"] * (1 + 2 * peers.GRAD_TOL)
    m = peers.compare(ours, peer)
    assert not m["agree"] and m["grad_silhouette_rel"] == pytest.approx(2 * peers.GRAD_TOL / (1 + 2 * peers.GRAD_TOL))


# ---- errors before anything runs ---------------------------------------------------------
def test_missing_peer_python(tmp_path, monkeypatch, capsys):
    with pytest.raises(InputError, match=r"--peer-python: no Python at .*setup_peers\.sh"):
        peers.peer_python(str(tmp_path / "nope" / "python"))
    monkeypatch.setattr(peers, "DEFAULT_PEER_PYTHON", tmp_path / ".venv-peers" / "bin" / "python")
    with pytest.raises(InputError, match=r"--peer-python not given and no .*\.venv-peers.*setup_peers\.sh"):
        peers.peer_python(None)
    assert main(["bench", "peers", *TINY, "--out", str(tmp_path / "out")]) == EXIT_INPUT
    assert "setup_peers.sh" in capsys.readouterr().err
    assert not (tmp_path / "out" / "peers.json").exists()


@pytest.mark.parametrize("option, value", [("--faces", "100"), ("--sizes", "0"), ("--repeats", "0"),
                                           ("--faces-per-pixel", "-1"), ("--peer-threads", "0")])
def test_bad_options(tmp_path, capsys, option, value):
    args = ["bench", "peers", "--peer-python", sys.executable, *TINY, option, value, "--out", str(tmp_path)]
    assert main(args) == EXIT_INPUT
    assert option in capsys.readouterr().err


# ---- end to end against the stand-in -----------------------------------------------------
def test_end_to_end_with_standin(tmp_path):
    code, result = run_standin(tmp_path)
    assert code == 0
    (row,) = result["rows"]
    assert row["agree"] and result["agree"]
    assert result["peer"]["renderer"].startswith("STAND-IN")
    # float32 kernels against the float64 reference and its central differences
    assert row["alpha_max"] < 1e-4 and row["rgb_max"] < 1e-4
    assert row["grad_silhouette_rel"] < peers.GRAD_TOL and row["grad_rel"] < peers.GRAD_TOL
    assert row["rgb_pixels_differ"] == 0 and row["pairs_peer"] is None and row["pairs_ours"] > 0
    for key in ("ours_fwd_ms", "ours_fwdbwd_ms", "peer_fwd_ms", "peer_fwdbwd_ms", "speedup_fwdbwd"):
        assert row[key] > 0
    assert result["provenance"]["cpu"] and "peer_python" in result["provenance"]["config"]
    assert (tmp_path / "peers.txt").read_text().startswith("ours: softras-cl")
    assert (tmp_path / "peers.png").stat().st_size > 0


@pytest.mark.parametrize("fault", ["sigma", "mirror"])
def test_a_wrong_peer_is_caught(tmp_path, monkeypatch, fault):
    monkeypatch.setenv("STANDIN_BREAK", fault)
    code, result = run_standin(tmp_path)
    assert code == EXIT_RESULT
    assert not result["agree"] and not result["rows"][0]["agree"]


def test_a_crashing_peer_is_an_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("STANDIN_BREAK", "crash")
    code, _ = run_standin(tmp_path)
    assert code == EXIT_RESULT
    assert "peer worker" in capsys.readouterr().err


# ---- the real peer, where it is installed --------------------------------------------------
@pytest.mark.skipif(not peers.DEFAULT_PEER_PYTHON.exists(), reason="no .venv-peers (scripts/setup_peers.sh)")
def test_real_pytorch3d_agrees_on_a_small_scene(tmp_path):
    assert main(["bench", "peers", "--sizes", "48", "--faces", "320", "--repeats", "1", "--out", str(tmp_path)]) == 0
    (row,) = json.loads((tmp_path / "peers.json").read_text())["rows"]
    assert row["agree"] and row["pairs_peer"] == row["pairs_ours"] and row["saturated_pixels"] == 0
