"""Provenance (softras_cl.provenance) in every params.json and benchmark JSON: versions, the
OpenCL device, the machine, the time, the command line and the effective configuration."""
import argparse
import json
import platform
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np
import pyopencl
import pytest

import softras_cl
from softras_cl.cl.device import select_device
from softras_cl.cli import main
from softras_cl.provenance import provenance, to_json

DATA = Path(__file__).resolve().parents[2] / "examples" / "data"


def assert_provenance(doc: dict) -> dict:
    """The real values of this process and device in doc["provenance"]; returns its config."""
    p = doc["provenance"]
    d = select_device()
    assert p["softras_cl_version"] == softras_cl.__version__
    assert p["python"] == platform.python_version() and p["numpy"] == np.__version__
    assert p["pyopencl"] == pyopencl.VERSION_TEXT
    assert p["device"] == dict(name=d.name, version=d.version)
    assert p["platform"] == dict(name=d.platform.name, version=d.platform.version)
    assert p["driver"] == d.driver_version
    assert p["cpu"] is None or isinstance(p["cpu"], str)
    assert p["os"] and isinstance(p["command_line"], list)
    assert datetime.fromisoformat(p["time"]).tzinfo is not None
    return p["config"]


def test_to_json_makes_plain_json():
    @dataclass
    class Config:
        size: tuple = (2, 3)
        path: Path = Path("a/b")
        scale: np.ndarray = np.float32(0.5)

    args = argparse.Namespace(out=Path("x"), func=print, sizes=(64,))
    doc = to_json(dict(config=Config(), options=args, array=np.arange(3), none=None))
    assert doc == dict(config=dict(size=[2, 3], path="a/b", scale=0.5), options=dict(out="x", sizes=[64]),
                       array=[0, 1, 2], none=None)
    json.dumps(provenance(Config()))


def test_bench_json_records_provenance(tmp_path):
    assert main(["bench", "raster", "--quick", "--out", str(tmp_path)]) == 0
    config = assert_provenance(json.loads((tmp_path / "raster.json").read_text()))
    assert config["options"]["quick"] is True and config["options"]["out"] == str(tmp_path)
    assert config["plan"]["sizes"] == [64] and config["plan"]["faces"] == [1280]


def test_fit_body_params_json_records_provenance(tmp_path):
    yy, xx = np.mgrid[:24, :24]
    np.save(tmp_path / "disc.npy", ((yy - 11.5) ** 2 + (xx - 11.5) ** 2 < 64).astype(float))
    out = tmp_path / "fit"
    assert main(["fit-body", str(tmp_path / "disc.npy"), "--silhouette", "--size", "16", "--budget", "fast",
                 "--out", str(out), "--no-progress"]) == 0
    config = assert_provenance(json.loads((out / "params.json").read_text()))
    assert config["fit"]["size"] == 16 and config["fit"]["background"] == [0.0, 0.0, 0.0]
    assert config["options"]["silhouette"] is True and config["options"]["budget"] == "fast"


@pytest.mark.slow
def test_fit_face_params_json_records_provenance(tmp_path):
    out = tmp_path / "fit"
    assert main(["fit-face", str(DATA / "astronaut.png"), "--landmarks", str(DATA / "landmarks" / "astronaut.pts"),
                 "--out", str(out), "--size", "48", "--budget", "fast", "--n-id", "2", "--n-exp", "2",
                 "--n-albedo", "1", "--no-progress"]) == 0
    config = assert_provenance(json.loads((out / "params.json").read_text()))
    assert config["fit"]["size"] == 48 and config["fit"]["n_id"] == 2
    assert isinstance(config["fit"]["photo_stages"][0], list)
    assert config["options"]["landmarks"] == str(DATA / "landmarks" / "astronaut.pts")
