"""scripts/face_host_parts.py: the face objective's per-evaluation parts, as JSON."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parents[3] / "scripts" / "face_host_parts.py"


def test_face_host_parts_times_every_part_of_both_stages(tmp_path):
    from softras_cl.fitting.model_cache import load_model
    from softras_cl.fitting.detection import resolve_landmarks
    from softras_cl.fitting.recipes import face
    from softras_cl.io.images import read_image

    data = SCRIPT.parents[1] / "examples" / "data"
    photo = read_image(data / "astronaut.png")[..., :3]
    points = resolve_landmarks(str(data / "astronaut.png"), str(data / "landmarks" / "astronaut.pts"))[0].points
    _, _, params = face.prepare_fit(photo, points, load_model("face", None, None), face.FaceFitConfig())
    np.savez(tmp_path / "params.npz", **params.values())
    run = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path / "params.npz"), "--evals", "2"],
                         capture_output=True, text=True, check=True)
    out = json.loads(run.stdout)
    photo_stage = out["photo-3"]
    assert photo_stage["robust_loss"] > 0 and photo_stage["shade_vertices"] > 0 and photo_stage["raster"] > 0
    assert photo_stage["host (main thread cpu - raster)"] < photo_stage["main thread cpu"]
    assert out["landmarks"]["raster"] == 0 and out["landmarks"]["geometry"] > 0
