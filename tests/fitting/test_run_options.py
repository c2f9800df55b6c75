"""fitting.run_options: every option of fit-face/fit-body reaches a batch item's job (its config
and run record) exactly as it reaches the single-photo command's, a manifest column reads like
the flag, and a batch rerun with another --coarse-mesh refits instead of skipping. Then: the
single-photo commands do not import the Dask cluster module."""
from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

from softras_cl.cli import build_parser
from softras_cl.cli import fit_body as body_cli
from softras_cl.cli import fit_face as face_cli
from softras_cl.cli import track_face as track_cli
from softras_cl.errors import InputError
from softras_cl.fitting.batch.items import collect_items
from softras_cl.fitting.batch.tasks import item_job, run_item
from softras_cl.fitting.jobs.body import body_job
from softras_cl.fitting.jobs.face_photo import FacePhotoJob
from softras_cl.fitting.run_options import BODY, FACE, TRACK

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "examples" / "data"
FILE = str(DATA / "landmarks" / "astronaut.pts")          # any file: a model option's record is its digest

# a value other than the default for every option of each fit, as typed on the command line
# (None: a switch); a new option needs its entry here
FACE_SAMPLES = dict(model=FILE, model_landmarks=FILE, budget="fast", size="128", photo_weight="30",
                    coarse_mesh="0.5", focal="900", fov="50", landmark_map="model", landmark_robust="3", dense_landmarks="1.5",
                    n_id="5", n_exp="6", n_albedo="7", objective="host")
BODY_SAMPLES = dict(model=FILE, silhouette=None, input="photo", background="0.5,0.5,0.5", budget="thorough", size="64",
                    distance="4.5", height="1.1", fov="40", coarse_mesh="0", robust_joints="3",
                    objective="host")
TRACK_SAMPLES = dict(model=FILE, fps="25", face="1", face_box="1,2,30,40", chunk="50", scan="60", keyframes="6",
                     identity_passes="1", budget="default", size="128", frame_iters="12", rotation_speed="0.1",
                     translation_speed="0.01", exp_speed="0.5", momentum="0.5", light_speed="0.3", smooth_lag="5",
                     export_meshes="obj")
CASES = [("face", FACE, face_cli, FACE_SAMPLES, str(DATA / "astronaut.png")),
         ("body", BODY, body_cli, BODY_SAMPLES, str(DATA / "astronaut.png"))]
SINGLE_JOBS = {"face": lambda photo, options: FacePhotoJob(photo, None, options),
               "body": lambda photo, options: body_job(photo, None, options)}     # as fit-face/fit-body make them


def _cli_args(command: str, photo: str, option=None, text=None):
    argv = [command, photo, "--out", "unused"]
    if option is not None:
        argv += [option.flag] if option.switch else [option.flag, text]
    args = build_parser(command).parse_args(argv)
    args.photo = args.target = photo
    args.landmarks = args.joints = None
    return args


def test_every_option_has_a_sample():
    assert set(FACE_SAMPLES) == set(FACE.names) and set(BODY_SAMPLES) == set(BODY.names)
    assert set(TRACK_SAMPLES) == set(TRACK.names)


def test_each_track_option_reaches_a_videos_config_and_record_as_the_single_video(tmp_path):
    """track-face on several videos: each option on the command line gives every video the
    config and run record that the single-video command gives (--face-box, a box in one video,
    goes per video in a manifest: the next test)."""
    from softras_cl.fitting.batch.videos import video_items
    from softras_cl.fitting.jobs.face_video import check_options, run_record
    from softras_cl.io.video import open_video

    from PIL import Image

    video = tmp_path / "frames"              # a folder of frames: --fps reaches it (a video file has its own times)
    video.mkdir()
    Image.new("RGB", (8, 8)).save(video / "0.png")
    video, source = str(video), open_video(video, 30.0)

    def single_and_item(option=None):
        argv = ["track-face", video, "--out", "unused"]
        if option is not None:
            argv += [option.flag, TRACK_SAMPLES[option.name]]
        values = track_cli._options(build_parser("track-face").parse_args(argv))
        item = video_items([video], values)[0] if option is None or option.name != "face_box" else None
        single = (check_options(values), run_record(source, values))
        return single, None if item is None else (check_options(item.opts), run_record(source, item.opts))

    (base_config, base_record), item = single_and_item()
    assert item == (base_config, base_record)
    for option in TRACK.options:
        (config, record), item = single_and_item(option)
        assert item in (None, (config, record)), option.name
        if option.field is not None or option.name == "budget":
            assert config != base_config, f"{option.flag} does not change the config"
        if option.name == "face_box":
            assert config[1] is not None
        elif option.recorded or option.file:
            assert record != base_record, f"{option.flag} is missing from the run record"


def test_a_track_manifest_column_reads_like_the_flag(tmp_path):
    from softras_cl.fitting.run_options import TRACK

    columns = {o.name.replace("_", "-"): TRACK_SAMPLES[o.name] for o in TRACK.options if not o.file}
    manifest = tmp_path / "videos.csv"
    with open(manifest, "w", newline="") as f:
        csv.writer(f).writerows([["video", *columns], ["clip.mp4", *columns.values()]])
    item = collect_items([], "track", manifest=manifest)[0]
    assert item.photo == str(tmp_path / "clip.mp4")
    for name, value in item.opts.items():
        args = build_parser("track-face").parse_args(["track-face", "v.mp4", "--out", "o", TRACK[name].flag,
                                                      TRACK_SAMPLES[name]])
        assert value == getattr(args, name), name


def test_an_unknown_option_is_named():
    with pytest.raises(InputError, match=r"unknown fit-body options \['colour'\] \(options: background, budget"):
        collect_items([str(DATA / "astronaut.png")], "body", dict(colour="red"))


@pytest.mark.parametrize("kind, fit, cli, samples, photo", CASES, ids=["face", "body"])
def test_each_option_reaches_the_batch_config_and_the_record_as_the_single_fit(kind, fit, cli, samples,
                                                                                 photo):
    def single_and_item(args):
        single = SINGLE_JOBS[kind](photo, cli._options(args))
        item = item_job(collect_items([photo], kind, cli._options(args))[0])     # what run_batch makes of it
        return (single.config, single.record()), (item.config, item.record())

    (base_config, base_record), item = single_and_item(_cli_args(fit.command, photo))
    assert item == (base_config, base_record)
    for option in fit.options:
        (config, record), item = single_and_item(_cli_args(fit.command, photo, option, samples[option.name]))
        assert item == (config, record), option.name        # the batch fits the same and skips on the same record
        if option.field is not None or option.name == "budget":
            assert config != base_config, f"{option.flag} does not change the config"
        if option.recorded or option.file:
            assert record != base_record, f"{option.flag} is missing from the run record"


@pytest.mark.parametrize("kind, fit, cli, samples, photo", CASES, ids=["face", "body"])
def test_a_manifest_column_reads_like_the_flag(tmp_path, kind, fit, cli, samples, photo):
    columns = {o.name.replace("_", "-"): "true" if o.switch else samples[o.name] for o in fit.options
               if not o.file}                    # a file cell is relative to the manifest: below
    manifest = tmp_path / "items.csv"
    with open(manifest, "w", newline="") as f:
        csv.writer(f).writerows([["photo", *columns], [photo, *columns.values()]])
    item = collect_items([], kind, manifest=manifest)[0]
    for name, value in item.opts.items():
        args = _cli_args(fit.command, photo, fit[name], samples[name])
        assert value == getattr(args, name), name
    manifest.write_text("photo,size\n" + photo + ",big\n")
    with pytest.raises(InputError, match="manifest column 'size': 'big' is not a int"):
        collect_items([], kind, manifest=manifest)
    manifest.write_text("photo,background\n" + photo + ",1,1,1\n")      # an unquoted comma
    with pytest.raises(InputError, match="line 2: more cells than the header"):
        collect_items([], kind, manifest=manifest)


def test_coarse_mesh_of_a_batch_item_and_its_rerun(tmp_path):
    """--coarse-mesh 0.5 fits with 0.5 and says so; the same again is skipped; another value
    (0: the model's own faces) refits."""
    import shutil

    photo = tmp_path / "in" / "face.png"
    photo.parent.mkdir()
    shutil.copy(DATA / "astronaut.png", photo)
    shutil.copy(DATA / "landmarks" / "astronaut.pts", photo.with_suffix(".pts"))
    small = dict(size=40, budget="fast", n_id=4, n_exp=4, n_albedo=2)
    out = tmp_path / "out"
    out.mkdir()

    def run(coarse_mesh):
        return run_item(collect_items([photo], "face", dict(small, coarse_mesh=coarse_mesh))[0], str(out))

    first = run(0.5)
    assert first["status"] == "ok", first["error"]
    assert json.loads((out / "face" / "complete.json").read_text())["options"]["coarse_mesh"] == 0.5
    fitted = json.loads((out / "face" / "params.json").read_text())["provenance"]["config"]["fit"]
    assert fitted["coarse_mesh"] == 0.5
    assert run(0.5)["status"] == "skipped"
    assert run(0.0)["status"] == "ok"
    assert json.loads((out / "face" / "complete.json").read_text())["options"]["coarse_mesh"] == 0.0
    assert run(None)["status"] == "ok"             # the default (not in the record) differs from 0 too
    assert "coarse_mesh" not in json.loads((out / "face" / "complete.json").read_text())["options"]
    assert run(FACE["coarse_mesh"].default)["status"] == "skipped"


SINGLE_FIT = """
import sys
from softras_cl.cli import build_parser
from softras_cl.cli import fit_body, fit_face
from softras_cl.fitting.jobs.body_target import BodyTargetJob
from softras_cl.fitting.jobs.face_photo import FacePhotoJob
from softras_cl.fitting.model_cache import load_model

face = build_parser("fit-face").parse_args(["fit-face", PHOTO, "--out", "o", "--coarse-mesh", "1"])
job = FacePhotoJob(PHOTO, None, fit_face._options(face))
job.read(), job.record()
body = build_parser("fit-body").parse_args(["fit-body", PHOTO, "--out", "o", "--size", "64"])
BodyTargetJob(PHOTO, None, fit_body._options(body)).record(), load_model("body")
print(sorted(m for m in sys.modules if m.startswith("softras_cl.fitting.batch") or m.split(".")[0] == "distributed"))
"""


def test_single_photo_commands_do_not_import_the_cluster_module():
    pytest.importorskip("distributed")          # else it could not be imported anyway
    script = SINGLE_FIT.replace("PHOTO", repr(str(DATA / "astronaut.png")))
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"     # after the detection fit-face prints
